"""``abh3 scan``: which ABH3 drives are on a bus, at which addresses, speaking which
protocol generation — without moving anything.

Only requests (PF 0xEA) are ever sent, never a DP0 command: a request makes a drive answer
with its DP0 reply or a broadcast packet and changes nothing in it. ``--listen-only``
sends nothing at all and learns from the traffic already there (a running supervisor, or
drives set to send periodically). The steps, each paced so a drive never sees a burst:

1. listen (a host already driving the bus shows itself here);
2. a DP0 request to all (destination 0xFF), then one to each address not heard yet;
3. broadcast 0 requested of every group 0–31 (to all): a drive answers only for its own;
4. broadcast 1 of each found drive's group: the velocity model of a 2021 drive.

The generation comes from the DP0 reply: a 2021 reply holds A, B, Y, X with Y = (A + B) / 2
and X = A − Y, which a 2023 reply (AY, BX, control word) only matches when the control word
is zero — then "2021" is only the likelier reading, said as such.
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from abh3_supervisor.core.foreign import Evidence
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.frames import Generation

log = logging.getLogger(__name__)
LISTEN_S = 0.3
COMMAND, SESSION = Evidence.COMMAND.value, Evidence.SESSION.value  # the commanding kinds
REPLY_WAIT_S = 0.15  # a drive answers a request within ~1 ms; slack for a loaded bus
PACE_S = 0.002  # between our requests: 500 frames/s at most, a few % of any ABH3 bitrate
GROUPS = range(32)


@dataclass
class Drive:
    address: int
    hosts: set[int] = field(default_factory=set)  # the hosts its DP0 replies went to
    generation: Generation | None = None
    certain: bool = False  # the reply's own shape said it
    error_word: int | None = None  # broadcast 0
    group: int | None = None
    travel_model: bool | None = None
    seen: set[str] = field(default_factory=set)  # "DP0 reply", "broadcast n"

    @property
    def generation_certain(self) -> bool:
        # a 2023 drive sets control bit 31 while an error is present: a zero control word
        # beside a non-zero error word (a drive never commanded has bit 22) rules 2023 out
        return self.certain or bool(self.generation is Generation.G2021 and self.error_word)

    @property
    def protocol(self) -> str:
        if self.generation is None:
            return "?"
        return self.generation.value + ("" if self.generation_certain else "?")


def guess_generation(data: bytes) -> tuple[Generation, bool]:
    """(generation, certain) from one DP0 reply's 8 bytes."""
    a, b, y, x = struct.unpack("<hhhh", data)
    consistent = abs(2 * y - (a + b)) <= 2 and abs(x - (a - y)) <= 2
    if not consistent:
        return Generation.G2023, True
    if data[4:8] == bytes(4) and a == b == 0:
        return Generation.G2021, False  # idle: a zero control word reads the same
    return Generation.G2021, True


class Findings:
    """What the frames on the bus say; fed every frame, sent or received (sans-I/O)."""

    def __init__(self, host: int) -> None:
        self.host = host
        self.drives: dict[int, Drive] = {}
        self.other_hosts: set[int] = set()  # nodes that sent requests: some host's
        # (source, destination) → (last data, frames since it was last settled)
        self._dp0_pairs: dict[tuple[int, int], tuple[bytes, int]] = {}
        self._tp_pairs: dict[tuple[int, int], int] = {}  # (source, destination) → frames
        # host → drive → frame kind → count: every host heard commanding a drive
        self.commanders: dict[int, dict[int, dict[str, int]]] = {}
        self.frames = 0

    def drive(self, address: int) -> Drive:
        return self.drives.setdefault(address, Drive(address))

    def observe(self, arbitration_id: int, data: bytes, ours: bool = False) -> None:
        self.frames += 1
        cid = ids.CanId.from_int(arbitration_id)
        if ours:
            return
        if cid.pf == ids.PF_REQUEST:
            self.other_hosts.add(cid.sa)
        elif cid.pf == ids.PF_BROADCAST and len(data) == 8:
            group, packet = cid.ps >> 3, cid.ps & 7
            drive = self.drive(cid.sa)
            drive.group = group
            drive.seen.add(f"broadcast {packet}")
            # packets 0 and 1 lay out alike in both generations as far as read here
            record = frames.decode_broadcast(packet, data, Generation.G2021)
            if isinstance(record, frames.Brd0):
                drive.error_word = record.error
            if isinstance(record, frames.Brd1) and drive.generation is Generation.G2021:
                control = record.control or 0  # 2021: the control word comes first
                drive.travel_model = bool(control & flags.layout(Generation.G2021).travel_model)
        elif cid.pf == ids.PF_SINGLE and len(data) == 8:
            _, count = self._dp0_pairs.get((cid.sa, cid.ps), (data, 0))
            self._dp0_pairs[cid.sa, cid.ps] = (data, count + 1)
            self._resolve()
        elif cid.pf in (ids.PF_TP_CM, ids.PF_TP_DT):  # a parameter session, either way
            self._tp_pairs[cid.sa, cid.ps] = self._tp_pairs.get((cid.sa, cid.ps), 0) + 1

    def _resolve(self) -> None:
        """A DP0 frame goes host → drive (a command) or drive → host (a reply): the host is
        us, a node that sent requests, or the one that is not a known drive."""
        hosts = self.other_hosts | {self.host}
        pending = {}
        for (source, destination), (data, count) in self._dp0_pairs.items():
            if destination in hosts or (source in self.drives and source not in hosts):
                self._reply(source, destination, data)
            elif source in hosts or destination in self.drives:
                self.drive(destination).seen.add(f"DP0 command from {source}")
                self._commanded(source, destination, COMMAND, count)
            else:
                pending[source, destination] = (data, count)
        self._dp0_pairs = pending

    def _commanded(self, host: int, drive: int, kind: str, count: int) -> None:
        kinds = self.commanders.setdefault(host, {}).setdefault(drive, {})
        kinds[kind] = kinds.get(kind, 0) + count

    def _reply(self, address: int, host: int, data: bytes) -> None:
        drive = self.drive(address)
        drive.hosts.add(host)
        drive.seen.add("DP0 reply")
        generation, certain = guess_generation(data)
        if certain or drive.generation is None:
            drive.generation, drive.certain = generation, certain
        if generation is Generation.G2023 and certain:
            reply = frames.decode_dp0_reply(data, generation)
            if isinstance(reply, frames.Dp0Reply2023):
                drive.travel_model = bool(reply.control & flags.layout(generation).travel_model)

    def finish(self) -> None:
        self._resolve()  # a node learnt to be a drive late settles its earlier DP0 frames
        # a session's frames go both ways: the host's are those to a drive, not from one
        for (source, destination), count in self._tp_pairs.items():
            if destination in self.drives and source not in self.drives:
                self._commanded(source, destination, SESSION, count)
        self._tp_pairs = {}

    def commanding(self) -> list[str]:
        """``host 2 commands drive 1: 25 × DP0 command, 3 × parameter session (TP)``, one
        line per host and drive (after :meth:`finish`)."""
        return [
            f"host {host} commands drive {drive}: "
            + ", ".join(f"{n} × {kind}" for kind, n in sorted(kinds.items()))
            for host, drives in sorted(self.commanders.items())
            for drive, kinds in sorted(drives.items())
        ]

    @property
    def unresolved(self) -> list[tuple[int, int]]:
        """DP0 traffic between two nodes neither known as the drive: (a, b) pairs."""
        return sorted(self._dp0_pairs)


class Scanner:
    """Runs the steps on a python-can bus; ``clock``/``sleep`` only pace and bound waits."""

    def __init__(
        self,
        bus: can.BusABC,
        host: int,
        *,
        listen_only: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bus, self.host, self.listen_only, self.clock = bus, host, listen_only, clock
        self.findings = Findings(host)
        self.sent = 0
        self.send_errors: list[str] = []

    def run(self, listen_s: float = LISTEN_S) -> Findings:
        self._listen(listen_s)
        if self.listen_only:
            self.findings.finish()
            return self.findings
        self._request(ids.ADDR_ALL, frames.PGN_DP0)
        self._listen(REPLY_WAIT_S)
        for address in range(ids.MAX_ADDRESS + 1):
            if address != self.host and address not in self.findings.drives:
                self._request(address, frames.PGN_DP0)
        self._listen(REPLY_WAIT_S)
        for group in GROUPS:
            if any(d.group is None for d in self.findings.drives.values()):
                self._request(ids.ADDR_ALL, frames.broadcast_pgn(group, 0))
        self._listen(REPLY_WAIT_S)
        for drive in list(self.findings.drives.values()):
            if drive.group is not None and drive.generation is Generation.G2021:
                self._request(drive.address, frames.broadcast_pgn(drive.group, 1))
        self._listen(REPLY_WAIT_S)
        self.findings.finish()
        return self.findings

    def _request(self, destination: int, pgn: int) -> None:
        msg = can.Message(
            arbitration_id=ids.request_id(destination, self.host),
            data=frames.encode_request(pgn),
            is_extended_id=True,
        )
        try:
            self.bus.send(msg, timeout=0.1)
            self.sent += 1
            self.findings.observe(msg.arbitration_id, bytes(msg.data), ours=True)
        except can.CanError as exc:
            self.send_errors.append(str(exc))
        self._listen(PACE_S)

    def _listen(self, seconds: float) -> None:
        end = self.clock() + seconds
        while (left := end - self.clock()) > 0:
            msg = self.bus.recv(left)
            if msg is None:
                break
            if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
                continue
            self.findings.observe(msg.arbitration_id, bytes(msg.data))


def report(findings: Findings, *, listen_only: bool) -> list[str]:
    lines = []
    if findings.drives:
        lines.append("address  protocol  group  model   answers host  seen")
    for d in sorted(findings.drives.values(), key=lambda d: d.address):
        model = "?" if d.travel_model is None else ("travel" if d.travel_model else "motor")
        hosts = ",".join(str(h) for h in sorted(d.hosts)) or "?"
        group = "?" if d.group is None else str(d.group)
        lines.append(
            f"{d.address:>7}  {d.protocol:<8}  {group:>5}  {model:<6}  {hosts:>12}  "
            + ", ".join(sorted(d.seen))
        )
    if any(not d.generation_certain for d in findings.drives.values()):
        lines.append(
            "protocol '2021?': an idle drive's reply reads the same in both generations; "
            "check the drive's CAN specification (or scan again while it reports a state)"
        )
    commanding = findings.commanding()
    if commanding:  # every host heard keeping a drive under command (core/foreign.py)
        lines.append("hosts commanding drives (another host: stop it before driving them):")
        lines += [f"  {line}" for line in commanding]
    for a, b in findings.unresolved:
        lines.append(f"DP0 frames between nodes {a} and {b}: one of them is a drive")
    others = findings.other_hosts - {findings.host}
    if others:
        lines.append(
            f"another host is on the bus (address {', '.join(map(str, sorted(others)))}): "
            "stop it before driving these drives from here"
        )
    if not findings.drives:
        lines.append(
            "no ABH3 found"
            + (
                ": nothing on the bus says so (listen-only learns only from traffic already there)"
                if listen_only
                else ": check power, wiring, termination, the bitrate and the drives' CAN "
                "function (parameter 0x4100 = 2) — docs/hardware.md"
            )
        )
    return lines


def starting_yaml(findings: Findings, interface: str, channel: str, bitrate: int) -> str:
    """A configuration to start from: every drive found, as a monitor (it moves nothing)."""
    bus = "can0" if channel == "can0" else "bus0"
    out = [
        "# written by `abh3 scan`: check every value against the drive's parameters",
        "# (docs/hardware.md), then set `role: command` on the units to drive",
        "buses:",
        f"  {bus}:",
        f"    interface: {interface}",
        f'    channel: "{channel}"',
        f"    bitrate: {bitrate}",
        "units:",
    ]
    for d in sorted(findings.drives.values(), key=lambda d: d.address):
        host = min(d.hosts) if d.hosts else findings.host
        out.append(f"  - name: drive{d.address}")
        out.append(f"    abh3_id: {d.address}")
        out.append(f"    host_id: {host}")
        generation = d.generation.value if d.generation else "2021"
        note = "" if d.generation_certain else "  # not certain: see the scan's note"
        out.append(f'    protocol: "{generation}"{note}')
        if d.group is not None:
            out.append(f"    brd_group: {d.group}")
        if d.travel_model is not None:
            out.append(f"    velocity_model: {'travel' if d.travel_model else 'motor'}")
        out.append("    role: monitor             # asks for status only; never moves a motor")
    if not findings.drives:
        out.append("  []  # no drive found")
    return "\n".join(out) + "\n"


def scan_command(
    interface: str,
    channel: str,
    bitrate: int,
    *,
    host: int,
    listen_only: bool,
    listen_s: float | None,
    as_yaml: bool,
) -> int:
    """``abh3 scan``: 0 when a drive was found, 1 when none was (or the bus cannot open),
    2 for an interface python-can does not know."""
    import sys

    from abh3_supervisor.config.interfaces import unknown_interface
    from abh3_supervisor.config.model import BusConfig
    from abh3_supervisor.errors import CommandError
    from abh3_supervisor.runtime.bus_runtime import open_bus

    if (problem := unknown_interface(interface)) is not None:  # a mistake on the command line
        raise CommandError(f"--interface {interface}: {problem}")
    cfg = BusConfig(name=channel, interface=interface, channel=channel, bitrate=bitrate)
    bus = open_bus(cfg, from_file=False)  # no file: its hints would name keys of none
    started = time.monotonic()
    try:
        scanner = Scanner(bus, host, listen_only=listen_only)
        findings = scanner.run(
            listen_s if listen_s is not None else (5.0 if listen_only else LISTEN_S)
        )
    finally:
        bus.shutdown()
    took = time.monotonic() - started
    lines = report(findings, listen_only=listen_only)
    if not findings.drives and interface == "virtual":
        lines.append(
            "python-can's virtual bus reaches only this process: drives simulated elsewhere "
            "cannot answer on it (`abh3 simulate` puts them on udp_multicast: "
            "docs/simulator.md)"
        )
    lines.append(
        f"scan of {interface} {channel}: {len(findings.drives)} drive(s) in {took:.1f} s, "
        f"{scanner.sent} request(s) sent, no command"
        + (
            f"; {len(scanner.send_errors)} send(s) failed: {scanner.send_errors[0]}"
            if scanner.send_errors
            else ""
        )
    )
    out = sys.stderr if as_yaml else sys.stdout
    for line in lines:
        print(line, file=out)
    if as_yaml:
        print(starting_yaml(findings, interface, channel, bitrate), end="")
    return 0 if findings.drives else 1
