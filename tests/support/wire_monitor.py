"""An independent wire monitor: the motion gate's invariants judged from the CAN frames.

Every frame on every simulated bus of a test passes :meth:`WireMonitor.frame` (the
``wire`` fixture in conftest.py taps python-can's virtual bus and the fake-clock
:class:`Timeline`). The monitor decodes DP0 commands and the J1939 transport itself, with
its own bit tables (protocol doc §3.1, §3.4, §5; params doc §1.3), and never looks at the
supervisor: what it knows besides the frames is the wiring — which node on a bus is a
simulated drive, and that drive's generation (the drive's, not the program's) — and what
the *operator* did, which a test states (:meth:`estop`, :meth:`clear`, :meth:`held`).

Invariants (names used by ``@pytest.mark.wire_allow(NAME, reason=…)`` opt-outs):

* ``well_formed``: a DP0 command is 8 bytes and sets no bit its generation leaves
  undefined; a request is 3 bytes (a PGN); transport control frames are 8 bytes and data
  frames 8 bytes with sequence numbers 1, 2, … in order (or again where a CTS asks).
* ``servo_write``: no data frame of a parameter *write* (TelABH3 ``CP`` with a value) goes
  to a drive while the last DP0 command to that drive had SERVO on.
* ``safe_exit``: when the host's bus closes, the last DP0 command it sent to each drive
  is the safe word: zero setpoints, every switch off but data select.
* ``estop``: from the first frame after the operator's e-stop until the clear, every DP0
  command has zero setpoints and START off; SERVO and brake release go off within
  :data:`ESTOP_POWER_OFF_S` (stop category 1) and none of SERVO, START, brake release
  rises until the clear.
* ``hold``: while a test declares a unit held (verification, a parameter write), each
  DP0 command to it is the safe word.
* ``identity``: before a drive's first DP0 reply, the commands to it carry zero setpoints
  and no bit beyond A/Y data select (bits 4-6: the only ones harmless in both
  generations) — nothing is energised before the drive's generation can be known.
* ``no_restart``: a drive that reported a SERVO on and then off while the host kept it
  commanded on (it rebooted, lost power, tripped) never reports it on again until the
  host has sent that SERVO bit off (the operator's new act) — read from the drive's own
  reports: the 2023 DP0 reply's control word, the 2021 broadcast 1's control word.
* ``ownership``: while a test declares a drive's owner gone (:meth:`WireMonitor.unowned`:
  the source that drove it left or went quiet), no command to it carries a non-zero
  setpoint later than :data:`OWNER_SLACK_S` after that.
* ``robot``: no drive is commanded a non-zero setpoint while another drive of its robot
  (the simulator's robots: the wheels' drives) has not answered within its command-zero
  timeout, or has reported every SERVO off, for longer than :data:`ROBOT_SLACK_S`.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

INVARIANTS = (
    "well_formed",
    "servo_write",
    "safe_exit",
    "estop",
    "hold",
    "identity",
    "no_restart",
    "robot",
    "ownership",
)
# an owner gone: its setpoint is zero from the next frame, one period of the slowest rate
OWNER_SLACK_S = 0.1
# the bits that mean the same harmless thing in both generations: A/Y data select
BOTH_SAFE = 0x70
# a drive's report reaches the host after a frame to its robot partner may have been built:
# one command period of the slowest configured rate (10 Hz)
ROBOT_SLACK_S = 0.1
# Stop category 1 (the lead's gate): zero and START off at once, SERVO and brake off once
# the drive reports the stop, at the latest this long after the e-stop ...
ESTOP_POWER_OFF_S = 1.0
# ... plus one command period late at most (the slowest configured rate is 10 Hz)
ESTOP_SLACK_S = 0.1

# --- the wire's own facts (protocol doc §2, §3) -------------------------------------------
PF_DP0, PF_REQUEST, PF_TP_CM, PF_TP_DT, PF_BROADCAST = 0xEF, 0xEA, 0xEC, 0xEB, 0xFF
TP_RTS, TP_ABORT = 0x10, 0xFF
SYN = 0x16


def _bits(*positions: int) -> int:
    return sum(1 << p for p in positions)


@dataclass(frozen=True, slots=True)
class Bits:
    """One generation's input ("operation") word, as far as motion goes (§5)."""

    servo: int
    start: int
    brake: int
    select: int
    defined: int


BITS = {
    "2021": Bits(
        servo=_bits(0, 12),
        start=_bits(1, 13),
        brake=_bits(28),
        select=_bits(4, 5, 6, 16, 17, 18),
        defined=_bits(*range(9), *range(12, 20), 23, 24, 25, 26, 28, 31),
    ),
    "2023": Bits(
        servo=_bits(0, 8),
        start=_bits(1, 9),
        brake=_bits(19),
        select=_bits(4, 5, 6, 12, 13, 14),
        defined=_bits(*range(23)),
    ),
}
# A drive of unknown generation: only the bits both generations agree on (A/Y SERVO and
# START) are judged; everything else could be select in one and motion in the other.
UNKNOWN = Bits(servo=_bits(0), start=_bits(1), brake=0, select=0xFFFFFFFF & ~0b11, defined=~0)


@dataclass(frozen=True, slots=True)
class Dp0:
    """A DP0 command as the wire carries it (§3.1)."""

    ay: int
    bx: int
    inputs: int

    @classmethod
    def decode(cls, data: bytes) -> Dp0:
        ay, bx, inputs = struct.unpack("<hhI", data)
        return cls(ay, bx, inputs)

    def describe(self, bits: Bits) -> str:
        on = [
            name
            for name, mask in (("SERVO", bits.servo), ("START", bits.start), ("BRAKE", bits.brake))
            if self.inputs & mask
        ]
        return f"setpoints {self.ay}/{self.bx} inputs 0x{self.inputs:08x} ({' '.join(on) or 'off'})"

    def safe(self, bits: Bits) -> bool:
        return self.ay == 0 and self.bx == 0 and self.inputs & ~bits.select == 0


def is_param_write(message: bytes) -> bool:
    """A TelABH3 request that writes: ``[FFFF] CP ADDR VALUE SUM`` (params doc §1.1, §1.3)
    once the SYN and 0xFF padding is stripped."""
    text = message.rstrip(bytes([SYN, 0xFF])).decode("ascii", "replace")
    if text.startswith("FFFFCP"):
        text = text[4:]
    return text.startswith("CP") and len(text) == 2 + 4 + 8 + 2


@dataclass(frozen=True, slots=True)
class Violation:
    invariant: str
    bus: str
    t: float
    unit: int
    frame: str
    why: str

    def __str__(self) -> str:
        return f"[{self.invariant}] bus {self.bus} t={self.t:.4f} unit {self.unit}: {self.why} — {self.frame}"


@dataclass
class _Message:
    """One host → drive transport message being sent (RTS, then DT frames)."""

    length: int
    packets: int
    data: bytearray = field(default_factory=bytearray)
    next_seq: int = 1
    servo_frame: tuple[float, str] | None = None  # the first DT sent while SERVO was on


@dataclass
class _Last:
    cmd: Dp0
    t: float


class BusWatch:
    """One bus: its drives, the last command to each, the host's open transports."""

    def __init__(self, monitor: WireMonitor, name: str, clock: Callable[[], float]) -> None:
        self.monitor, self.name, self.clock = monitor, name, clock
        self.sims: list[object] = []  # simulated drives' SimBus objects (looked up lazily)
        self.drive_senders: set[object] = set()
        self.learned: set[int] = set()  # drive addresses seen in requests and broadcasts
        self.declared: dict[int, str] = {}
        self.last: dict[int, _Last] = {}
        self.by_sender: dict[object, dict[int, _Last]] = {}
        self.transports: dict[tuple[int, int], _Message] = {}
        self.estop_from: float | None = None
        self.powered_late: set[int] = set()
        self.closed = False
        self.replied: dict[int, float] = {}  # drive → when it last sent a DP0 reply
        self.servo_reported: dict[int, tuple[int, float]] = {}  # drive → (SERVO bits, since)
        self.dropped: dict[int, int] = {}  # drive → SERVO bits it dropped under the host
        self.restarted: set[int] = set()  # said once per drive

    # ---------------------------------------------------------------- who is who

    def generation(self, address: int) -> str | None:
        if address in self.declared:
            return self.declared[address]
        for sim in self.sims:
            drive = getattr(sim, "drives", {}).get(address)
            if drive is not None:
                return str(getattr(drive.generation, "value", drive.generation))
        return None

    def is_drive(self, address: int) -> bool:
        return self.generation(address) is not None or address in self.learned

    def bits(self, address: int) -> Bits:
        return BITS.get(self.generation(address) or "", UNKNOWN)

    # ---------------------------------------------------------------- frames

    def frame(self, sender: object, arbitration_id: int, data: bytes, t: float) -> None:
        pf, ps, sa = arbitration_id >> 16 & 0xFF, arbitration_id >> 8 & 0xFF, arbitration_id & 0xFF
        from_drive = sender in self.drive_senders
        if pf == PF_BROADCAST:
            self.learned.add(sa)
        elif pf == PF_REQUEST and not from_drive and ps != 0xFF:
            self.learned.add(ps)
        if from_drive:
            self._drive_frame(sa, pf, ps, data, t)
            return
        if not self.is_drive(ps):
            return  # a frame to no drive: nothing the gate decides
        shown = f"{arbitration_id:08x} [{data.hex(' ')}]"
        if pf == PF_REQUEST and len(data) != 3:
            self._report("well_formed", t, ps, shown, f"request of {len(data)} bytes, not 3")
        elif pf == PF_DP0:
            self._command(sender, ps, data, t, shown)
        elif pf == PF_TP_CM:
            self._transport_control(sa, ps, data, t, shown)
        elif pf == PF_TP_DT:
            self._transport_data(sa, ps, data, t, shown)

    def _report(self, invariant: str, t: float, unit: int, frame: str, why: str) -> None:
        self.monitor.report(Violation(invariant, self.name, t, unit, frame, why))

    def _command(self, sender: object, unit: int, data: bytes, t: float, shown: str) -> None:
        bits = self.bits(unit)
        if len(data) != 8:
            self._report("well_formed", t, unit, shown, f"DP0 command of {len(data)} bytes")
            return
        cmd = Dp0.decode(data)
        if cmd.inputs & ~bits.defined & 0xFFFFFFFF:
            why = f"bits undefined in its generation: 0x{cmd.inputs & ~bits.defined:08x}"
            self._report("well_formed", t, unit, shown, why)
        shown = f"{shown} = {cmd.describe(bits)}"
        before = self.last.get(unit)
        if unit not in self.replied and (cmd.ay or cmd.bx or cmd.inputs & ~BOTH_SAFE):
            self._report("identity", t, unit, shown, "energy before the drive ever answered")
        if unit in self.dropped:  # SERVO sent off: switching it on again is a new act
            self.dropped[unit] &= cmd.inputs
        if cmd.ay or cmd.bx:
            self._judge_robot(unit, t, shown)
            gone = self.monitor.unowned_since.get(unit)
            if gone is not None and t - gone > OWNER_SLACK_S:
                why = f"a setpoint {t - gone:.3f} s after its owner left"
                self._report("ownership", t, unit, shown, why)
        if self.estop_from is not None:
            self._judge_estop(unit, cmd, before, bits, t, shown)
        held = self.monitor.holds.get(unit)
        if held is not None and not cmd.safe(bits) and unit not in self.monitor.held_moving:
            self.monitor.held_moving.add(unit)  # once per hold: the first frame says it
            self._report("hold", t, unit, shown, f"held ({held}) yet not the safe word")
        self.last[unit] = _Last(cmd, t)
        self.by_sender.setdefault(sender, {})[unit] = _Last(cmd, t)
        self.monitor.counted("dp0")

    def _partners(self, unit: int) -> set[int]:
        """The other drives of ``unit``'s robots, as the simulator built them."""
        found: set[int] = set()
        for sim in self.sims:
            for robot in getattr(sim, "_robots_of", {}).get(unit, ()):
                found.update(wheel.address for wheel in robot.wheels)
        found.discard(unit)
        return found

    def _command_zero_s(self, address: int) -> float:
        for sim in self.sims:
            drive = getattr(sim, "drives", {}).get(address)
            if drive is not None:
                return float(getattr(drive, "command_zero_ms", 500)) / 1000
        return 0.5

    def _judge_robot(self, unit: int, t: float, shown: str) -> None:
        for other in self._partners(unit):
            heard = self.replied.get(other)
            if heard is None or t - heard > self._command_zero_s(other) + ROBOT_SLACK_S:
                why = f"drive {other} of its robot has not answered" + (
                    f" for {t - heard:.3f} s" if heard is not None else ""
                )
                self._report("robot", t, unit, shown, f"motion while {why}")
                continue
            servo, since = self.servo_reported.get(other, (-1, 0.0))
            if servo == 0 and t - since > ROBOT_SLACK_S:
                why = f"drive {other} of its robot has reported every SERVO off since t={since:.4f}"
                self._report("robot", t, unit, shown, f"motion while {why}")

    def _drive_frame(self, drive: int, pf: int, ps: int, data: bytes, t: float) -> None:
        """A drive's own frame: its replies and its report of its switches."""
        if len(data) != 8:
            return
        generation = self.generation(drive)
        if pf == PF_DP0:
            self.replied[drive] = t
            if generation == "2023":  # the control word: the same SERVO bits as the input
                self._servo_report(drive, struct.unpack_from("<I", data, 4)[0], t)
        elif pf == PF_BROADCAST and ps & 7 == 1 and generation == "2021":
            self._servo_report(drive, struct.unpack_from("<I", data, 0)[0], t)

    def _servo_report(self, drive: int, control: int, t: float) -> None:
        bits = self.bits(drive)
        on = control & bits.servo
        before, since = self.servo_reported.get(drive, (0, t))
        self.servo_reported[drive] = (on, since if on == before else t)
        last = self.last.get(drive)
        commanded = last.cmd.inputs & bits.servo if last is not None else 0
        self.dropped[drive] = self.dropped.get(drive, 0) | before & ~on & commanded
        back = on & ~before & self.dropped.get(drive, 0)
        if back and drive not in self.restarted:
            self.restarted.add(drive)
            frame = f"last DP0 {last.cmd.describe(bits)}" if last is not None else "-"
            why = (
                f"the drive reports SERVO 0x{back:08x} on again after dropping it, and the "
                "host never sent it off meanwhile: an automatic restart"
            )
            self._report("no_restart", t, drive, frame, why)

    def _judge_estop(
        self, unit: int, cmd: Dp0, before: _Last | None, bits: Bits, t: float, shown: str
    ) -> None:
        assert self.estop_from is not None
        if cmd.ay or cmd.bx or cmd.inputs & bits.start:
            self._report("estop", t, unit, shown, "setpoint or START while e-stopped")
        power = bits.servo | bits.brake
        late = t - self.estop_from > ESTOP_POWER_OFF_S + ESTOP_SLACK_S
        if late and cmd.inputs & power and unit not in self.powered_late:
            self.powered_late.add(unit)  # once per unit and e-stop: the first frame says it
            why = f"SERVO/brake release still on {t - self.estop_from:.3f} s after the e-stop"
            self._report("estop", t, unit, shown, why)
        rising = cmd.inputs & ~(before.cmd.inputs if before else 0) & (power | bits.start)
        if rising:
            self._report(
                "estop", t, unit, shown, f"bits 0x{rising:08x} switched on while e-stopped"
            )

    def _servo_on(self, unit: int) -> bool:
        last = self.last.get(unit)
        return last is not None and bool(last.cmd.inputs & self.bits(unit).servo)

    def _transport_control(self, host: int, unit: int, data: bytes, t: float, shown: str) -> None:
        if len(data) != 8:
            self._report("well_formed", t, unit, shown, f"transport control of {len(data)} bytes")
            return
        if data[0] == TP_RTS:
            self.transports[(host, unit)] = _Message(data[1] | data[2] << 8, data[3])
            self.monitor.counted("rts")
        elif data[0] == TP_ABORT:
            self.transports.pop((host, unit), None)

    def _transport_data(self, host: int, unit: int, data: bytes, t: float, shown: str) -> None:
        message = self.transports.get((host, unit))
        if message is None:
            return  # DT frames of a message whose RTS this monitor did not see
        seq = data[0] if data else 0
        if len(data) != 8 or not 1 <= seq <= min(message.next_seq, message.packets):
            why = f"DT frame of {len(data)} bytes, sequence {seq} (next {message.next_seq})"
            self._report("well_formed", t, unit, shown, why)
            self.transports.pop((host, unit), None)
            return
        # in order, or again from an earlier packet when the drive's CTS asks for it
        message.data[(seq - 1) * 7 :] = data[1:]
        message.next_seq = seq + 1
        if self._servo_on(unit) and message.servo_frame is None:
            last = self.last[unit]
            message.servo_frame = (
                t,
                f"{shown} after DP0 {last.cmd.describe(self.bits(unit))} at t={last.t:.4f}",
            )
        if message.next_seq > message.packets:
            del self.transports[(host, unit)]
            body = bytes(message.data[: message.length])
            if message.servo_frame is not None and is_param_write(body):
                at, frame = message.servo_frame
                why = f"parameter write {body.rstrip(bytes([SYN, 0xFF]))!r} sent with SERVO on"
                self._report("servo_write", at, unit, frame, why)

    # ---------------------------------------------------------------- ways out

    def sender_closed(self, sender: object) -> None:
        """``sender`` (the host's bus) closed: its last command to each drive is the safe word."""
        for unit, last in self.by_sender.pop(sender, {}).items():
            bits = self.bits(unit)
            if not last.cmd.safe(bits):
                frame = f"last DP0 {last.cmd.describe(bits)}"
                self._report(
                    "safe_exit", last.t, unit, frame, "the bus closed with this as the last command"
                )


class WireMonitor:
    """The invariants over every bus of one test; violations kept until :meth:`check`."""

    def __init__(self) -> None:
        self.buses: dict[object, BusWatch] = {}
        self.violations: list[Violation] = []
        self.allowed: set[str] = set()
        self.holds: dict[int, str] = {}
        self.held_moving: set[int] = set()
        self.unowned_since: dict[int, float] = {}  # drive → when its owner left
        self.estopped = False
        self.seen = {"dp0": 0, "rts": 0}  # DP0 commands, transport RTSs to drives so far
        self._lock = threading.Lock()  # the loop's thread reports, the test's checks
        self._counted = threading.Condition()

    # ---------------------------------------------------------------- wiring

    def bus(self, key: object, name: str, clock: Callable[[], float] = time.monotonic) -> BusWatch:
        watch = self.buses.get(key)
        if watch is None or watch.closed:
            watch = self.buses[key] = BusWatch(self, name, clock)
            if self.estopped:
                watch.estop_from = clock()
        return watch

    def drives(self, key: object, sim: object, sender: object) -> None:
        """``sender`` on bus ``key`` is simulated drives (a SimBus: their generations)."""
        watch = self.buses[key]
        watch.sims.append(sim)
        watch.drive_senders.add(sender)

    def declare(self, key: object, address: int, generation: str) -> None:
        """A drive that is no simulator's (a hand-written fake): its generation."""
        self.buses[key].declared[address] = generation

    def frame(
        self, key: object, sender: object, arbitration_id: int, data: bytes, t: float
    ) -> None:
        self.buses[key].frame(sender, arbitration_id, bytes(data), t)

    def closed(self, key: object, sender: object, last: bool = False) -> None:
        """``sender`` left bus ``key``; ``last``: nobody is left on it (a new bus by the
        same name later is another bus)."""
        watch = self.buses.get(key)
        if watch is not None:
            watch.sender_closed(sender)
            watch.closed = last

    def counted(self, kind: str) -> None:
        with self._counted:
            self.seen[kind] += 1
            self._counted.notify_all()

    def wait_commands(self, count: int, timeout: float) -> bool:
        """Until ``count`` more DP0 commands crossed the wire (real-time buses: the gate
        has decided that many frames since), or ``timeout`` passed (a drive that does not
        answer is commanded more slowly): whether they did."""
        return self.wait_seen("dp0", count, timeout)

    def wait_seen(self, kind: str, count: int, timeout: float) -> bool:
        """Until ``count`` more frames of ``kind`` (``dp0``: commands, ``rts``: the start
        of a transport to a drive) crossed the wire, or ``timeout`` passed."""
        with self._counted:
            goal = self.seen[kind] + count
            return self._counted.wait_for(lambda: self.seen[kind] >= goal, timeout)

    # ---------------------------------------------------------------- the operator

    def estop(self) -> None:
        """The operator's e-stop took effect (its request was answered): judged from the
        next frame on every bus, until :meth:`clear`."""
        self.estopped = True
        for watch in self.buses.values():
            if watch.estop_from is None:
                watch.estop_from = watch.clock()

    def clear(self) -> None:
        """The operator is about to clear the e-stop: frames from now on are not judged."""
        self.estopped = False
        for watch in self.buses.values():
            watch.estop_from = None
            watch.powered_late.clear()

    @contextlib.contextmanager
    def held(self, address: int, why: str = "held") -> Iterator[None]:
        """Every DP0 command to drive ``address`` (on any bus) in the block is the safe
        word: enter once the hold is in effect, leave before releasing it."""
        self.holds[address] = why
        try:
            yield
        finally:
            self.holds.pop(address, None)
            self.held_moving.discard(address)

    @contextlib.contextmanager
    def unowned(self, address: int, since: float) -> Iterator[None]:
        """The owner of drive ``address``'s motion left (or went quiet) at ``since`` (the
        bus's clock): in the block, no command to it may carry a setpoint later than
        :data:`OWNER_SLACK_S` after that. Leave it before a new owner commands."""
        self.unowned_since[address] = since
        try:
            yield
        finally:
            self.unowned_since.pop(address, None)

    # ---------------------------------------------------------------- verdicts

    def report(self, violation: Violation) -> None:
        if violation.invariant not in self.allowed:
            with self._lock:
                self.violations.append(violation)

    def check(self) -> None:
        """Fail with every violation seen so far (each once)."""
        with self._lock:
            found, self.violations = self.violations, []
        if found:
            shown = "\n  ".join(str(v) for v in found[:20])
            more = f"\n  … and {len(found) - 20} more" if len(found) > 20 else ""
            raise AssertionError(f"wire monitor: {len(found)} violation(s):\n  {shown}{more}")

    def commanded(self) -> int:
        """How many drives were commanded so far (for tests of the tap itself)."""
        return sum(len(w.last) for w in self.buses.values())
