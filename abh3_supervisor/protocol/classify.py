"""Whole-frame decoding for recordings: identifier + payload → addressed record.

DP0 command and reply share PF 0xEF; which is which follows from the addresses, so the
classifier is told the host addresses (the seed's default host 2 unless configured).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum

from abh3_supervisor.protocol.frames import (
    Broadcast,
    Dp0Command,
    Dp0Reply,
    Generation,
    Request,
    Unknown,
    decode_broadcast,
    decode_dp0_command,
    decode_dp0_reply,
    decode_request,
)
from abh3_supervisor.protocol.ids import (
    PF_BROADCAST,
    PF_REQUEST,
    PF_SINGLE,
    PF_TP_CM,
    PF_TP_DT,
    CanId,
)


class Direction(StrEnum):
    TO_DRIVE = "host->drive"
    FROM_DRIVE = "drive->host"


class Kind(StrEnum):
    DP0_COMMAND = "dp0_command"
    DP0_REPLY = "dp0_reply"
    REQUEST = "request"
    BROADCAST = "broadcast"
    TRANSPORT = "transport"
    UNKNOWN = "unknown"


Payload = Dp0Command | Dp0Reply | Request | Broadcast | Unknown


@dataclass(frozen=True)
class AddressBook:
    """What the classifier knows of the bus: host addresses and each drive's generation."""

    hosts: frozenset[int] = frozenset({2})
    generations: Mapping[int, Generation] = field(default_factory=dict)
    default_generation: Generation = Generation.G2021

    def generation(self, abh3: int) -> Generation:
        return self.generations.get(abh3, self.default_generation)


@dataclass(frozen=True, slots=True)
class DecodedFrame:
    kind: Kind
    payload: Payload
    priority: int = 0
    direction: Direction | None = None
    abh3: int | None = None
    host: int | None = None
    group: int | None = None
    packet: int | None = None


def classify(
    arbitration_id: int, data: bytes, is_extended: bool, book: AddressBook
) -> DecodedFrame:
    """Decode any frame; never raises (unknown frames say why they are unknown)."""
    if not is_extended:
        return DecodedFrame(Kind.UNKNOWN, Unknown("11-bit identifier: not an ABH3 frame"))
    cid = CanId.from_int(arbitration_id)
    if cid.dp:
        return DecodedFrame(Kind.UNKNOWN, Unknown("data page 1 is reserved"), cid.priority)
    if cid.pf == PF_SINGLE:
        if cid.sa in book.hosts:
            return DecodedFrame(
                Kind.DP0_COMMAND,
                decode_dp0_command(data, book.generation(cid.ps)),
                cid.priority,
                Direction.TO_DRIVE,
                abh3=cid.ps,
                host=cid.sa,
            )
        return DecodedFrame(
            Kind.DP0_REPLY,
            decode_dp0_reply(data, book.generation(cid.sa)),
            cid.priority,
            Direction.FROM_DRIVE,
            abh3=cid.sa,
            host=cid.ps,
        )
    if cid.pf == PF_REQUEST:
        return DecodedFrame(
            Kind.REQUEST,
            decode_request(data),
            cid.priority,
            Direction.TO_DRIVE,
            abh3=cid.ps,
            host=cid.sa,
        )
    if cid.pf == PF_BROADCAST:
        group, packet = cid.ps >> 3, cid.ps & 7
        return DecodedFrame(
            Kind.BROADCAST,
            decode_broadcast(packet, data, book.generation(cid.sa)),
            cid.priority,
            Direction.FROM_DRIVE,
            abh3=cid.sa,
            group=group,
            packet=packet,
        )
    if cid.pf in (PF_TP_CM, PF_TP_DT):
        return DecodedFrame(
            Kind.TRANSPORT,
            Unknown("J1939 transport frame (parameter access, not decoded)"),
            cid.priority,
        )
    return DecodedFrame(
        Kind.UNKNOWN, Unknown(f"PDU format 0x{cid.pf:02X} is not ABH3"), cid.priority
    )
