"""29-bit J1939-style identifiers (protocol doc §2)."""

from __future__ import annotations

from dataclasses import dataclass

PF_SINGLE = 0xEF  # §3.1 single packet DP0: command and feedback
PF_REQUEST = 0xEA  # §3.2 request
PF_BROADCAST = 0xFF  # §3.3 broadcast packets
PF_TP_CM = 0xEC  # §3.4 transport control
PF_TP_DT = 0xEB  # §3.4 transport data
ADDR_ALL = 0xFF
MAX_ADDRESS = 253  # 0–253 are unit/host addresses; 254/255 are reserved
_PRIORITY_SHIFT = 26
MATCH_MASK = (1 << _PRIORITY_SHIFT) - 1  # everything except the priority bits


@dataclass(frozen=True, slots=True)
class CanId:
    """A decomposed 29-bit identifier."""

    priority: int
    pf: int
    ps: int
    sa: int
    dp: int = 0

    def to_int(self) -> int:
        return (
            (self.priority & 7) << _PRIORITY_SHIFT
            | (self.dp & 1) << 24
            | (self.pf & 0xFF) << 16
            | (self.ps & 0xFF) << 8
            | (self.sa & 0xFF)
        )

    @classmethod
    def from_int(cls, arbitration_id: int) -> CanId:
        return cls(
            priority=(arbitration_id >> _PRIORITY_SHIFT) & 7,
            dp=(arbitration_id >> 24) & 1,
            pf=(arbitration_id >> 16) & 0xFF,
            ps=(arbitration_id >> 8) & 0xFF,
            sa=arbitration_id & 0xFF,
        )


def without_priority(arbitration_id: int) -> int:
    """The part of an identifier replies are matched on (§2: ignore the priority)."""
    return arbitration_id & MATCH_MASK


def dp0_command_id(abh3: int, host: int, priority: int = 0) -> int:
    """Host → ABH3 DP0 command, e.g. ``0x00EF0102`` for the defaults."""
    return CanId(priority, PF_SINGLE, abh3, host).to_int()


def dp0_reply_id(abh3: int, host: int) -> int:
    """ABH3 → host DP0 reply (priority bits zero; match with :func:`without_priority`)."""
    return CanId(0, PF_SINGLE, host, abh3).to_int()


def request_id(destination: int, host: int, priority: int = 0) -> int:
    """Host request to one drive or to all (``destination=ADDR_ALL``)."""
    return CanId(priority, PF_REQUEST, destination, host).to_int()


def broadcast_id(abh3: int, group: int, packet: int) -> int:
    """ABH3 broadcast packet ``packet`` of ``group`` (e.g. ``0x00FF2801``)."""
    return CanId(0, PF_BROADCAST, group * 8 + packet, abh3).to_int()
