"""The motion gate: the one place that decides what a unit's command frame says.

Every DP0 command word and setpoint is built here, from explicit state, and nowhere
else (the rest of the program asks for switches and motion; the gate decides what
reaches the wire). The state it decides from, most restrictive first:

- **stopping** — the way out (normal end, signal, fatal error): the safe word, final;
- **another host** commands the unit's drive, or a drive of its robot (core/foreign.py):
  the safe word, until the operator clears it once that host has been quiet;
- **a parameter write** in flight on the unit (a lock, taken before the write and held
  until it ends): the safe word;
- **held** by ``verify: refuse`` until the drive is verified: the safe word;
- **the e-stop latch** (IEC 60204-1 stop category 1): zero and START off at once, the
  drive decelerating on its own ramp with its servo on; SERVO and brake release off as
  soon as the drive reports it stopped, at the latest :data:`ESTOP_POWER_OFF_S` after;
- **the owner** of the unit's motion: a non-zero setpoint only while the source that
  owns it in the arbitration (core/inputs.py) still owns it; otherwise zero.

"The safe word" is :meth:`Layout.safe`: everything off but data select (SERVO, START,
brake release, torque, …) with zero setpoints. Entering a restricted state also
*consumes* what it refuses (the switches it forces off are forgotten, the arbitration is
voided), so nothing comes back on its own when the state ends: only a command given
after that moves anything. docs/safety.md is the reference for these states.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from abh3_supervisor.config.model import ControlMode, Role
from abh3_supervisor.core.readiness import switches
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY

if TYPE_CHECKING:
    from abh3_supervisor.core.state import UnitState

# the e-stop's power-off: SERVO and brake release go off once the drive reports both axes
# below this speed [min⁻¹] in an answer to a frame sent after the e-stop …
STOPPED_BELOW = 2.0
# … or this long after the e-stop at the latest, whatever the drive says (a drive that does
# not answer, an axis held by a load, current control)
ESTOP_POWER_OFF_S = 1.0


def moving_switches(layout: flags.Layout) -> int:
    """The input bits that let a motor move or a load fall: SERVO, START, brake release."""
    return layout.servo.both | layout.start.both | layout.brake_release


def idle_axes(unit: UnitState) -> int:
    """SERVO and START of the unit's axes that drive no wheel of its robot: never on."""
    return switches(unit.layout, (a for a in (0, 1) if a not in unit.wheels))


@dataclass(frozen=True, slots=True)
class Word:
    """What one unit's next command frame says."""

    inputs: int
    ay: float  # min⁻¹, or % in current control
    bx: float
    kind: ControlMode

    def payload(self) -> bytes:
        scale = CURRENT if self.kind is ControlMode.CURRENT else VELOCITY
        return frames.encode_dp0_command(
            scale.to_raw(self.ay)[0], scale.to_raw(self.bx)[0], self.inputs
        )


@dataclass
class EStop:
    """The latched e-stop: when it was given, and the units whose power is off."""

    t: float
    powered_off: set[str] = field(default_factory=set)


class MotionGate:
    """The explicit state every command frame is decided from (see the module docstring).

    Sans-I/O and side-effect free but for its own state: the Supervisor asks it what a unit
    may do (``refuse_*`` raise :class:`CommandError` saying why not) and what its frame
    says (:meth:`word`), and tells it what changed.
    """

    def __init__(self) -> None:
        self.estop: EStop | None = None
        self.stopping = False
        # the way out's controlled stop (stop category 1): the units still ramping down,
        # START off and zero with SERVO and brake release kept until each reports standing
        self.ramping: set[str] = set()
        self._writes: dict[str, int] = {}  # unit → parameter writes in flight
        # unit → why another host stops it (core/foreign.py); cleared by the operator only
        self.foreign: dict[str, str] = {}

    # ------------------------------------------------------------ state

    def latch(self, t: float) -> None:
        if self.estop is None:
            self.estop = EStop(t)

    def clear(self) -> None:
        self.estop = None

    def power_off(self, unit: str) -> bool:
        """The e-stop's second step for ``unit``; True if it was still to be done."""
        if self.estop is None or unit in self.estop.powered_off:
            return False
        self.estop.powered_off.add(unit)
        return True

    @contextmanager
    def writing(self, unit: UnitState) -> Iterator[None]:
        """Hold the parameter-write lock of ``unit`` for the ``with`` block. Refused while
        this supervisor commands its SERVO on (switch it off first)."""
        if unit.inputs & unit.layout.servo.both:
            raise CommandError("this supervisor commands its servo ON (switch it off first)")
        self._writes[unit.name] = self._writes.get(unit.name, 0) + 1
        try:
            yield
        finally:
            self._writes[unit.name] -= 1
            if not self._writes[unit.name]:
                del self._writes[unit.name]

    def written(self, unit: str) -> bool:
        return unit in self._writes

    # ------------------------------------------------------------ decisions

    def blocked(self, unit: UnitState) -> str | None:
        """Why nothing may be switched on or move on ``unit`` at all now, or None."""
        if self.stopping:
            return "the supervisor is stopping: commands are refused"
        if unit.cfg.role is not Role.COMMAND:
            return f"unit '{unit.name}' is configured role: monitor and takes no commands"
        if (why := self.foreign.get(unit.name)) is not None:
            return f"unit '{unit.name}' is stopped: {why}"
        if unit.name in self._writes:
            return (
                f"a parameter write is in flight on unit '{unit.name}': SERVO, START and "
                "motion are refused until it ends"
            )
        if held := unit.verify.holds():
            return f"unit '{unit.name}' is held at its idle word: {held}"
        if unit.identified not in (None, unit.cfg.protocol):
            return (
                f"unit '{unit.name}' answers as a {unit.identified} drive but the file says "
                f'protocol: "{unit.cfg.protocol}": held at a word safe in both generations'
            )
        return None

    def refuse_inputs(self, unit: UnitState, new: int) -> None:
        """Refuse an input word that switches on what the unit's state forbids."""
        layout = unit.layout
        rising = new & ~unit.inputs
        if not rising:
            return
        # a held unit may still change what only picks a table, and reset an error
        harmless = layout.select_mask | layout.error_reset
        if (why := self.blocked(unit)) is not None and rising & ~harmless:
            raise CommandError(why)
        if self.estop is not None and rising & moving_switches(layout):
            raise CommandError(
                "emergency stop is latched: clear it before SERVO, START or brake release"
            )

    def refuse_motion(self, unit: UnitState, ay: float, bx: float) -> None:
        """Refuse a setpoint the unit's state forbids (zero is always allowed)."""
        if not (ay or bx):
            return
        if (why := self.blocked(unit)) is not None:
            raise CommandError(why)
        if self.estop is not None:
            raise CommandError("emergency stop is latched: clear it before commanding motion")

    def restricted(self, unit: UnitState) -> bool:
        """The unit sends the safe word whatever it was asked (stopping, another host, a
        write, held)."""
        return self.stopping or self._held(unit)

    def _held(self, unit: UnitState) -> bool:
        return (
            unit.name in self.foreign
            or unit.name in self._writes
            or unit.verify.holds() is not None
            or (self.estop is not None and unit.name in self.estop.powered_off)
        )

    def word(self, unit: UnitState, owned: bool, ready: bool = True) -> Word:
        """The unit's command frame now. ``owned``: the source that set the unit's
        setpoint still owns the unit in the arbitration (core/inputs.py); ``ready``: every
        drive of its robot reports ready (core/readiness.py)."""
        if unit.identified is not unit.cfg.protocol:
            # identity before energy: until its replies show the declared generation the
            # drive gets only the probe, which means the same harmless thing in both
            return Word(flags.ID_PROBE, 0.0, 0.0, ControlMode.VELOCITY)
        layout, setpoint = unit.layout, unit.setpoint
        inputs = unit.inputs & ~idle_axes(unit)  # an axis that drives no wheel stays off
        if self.stopping:
            if unit.name in self.ramping and not self._held(unit):  # category 1, first step
                return Word(inputs & ~layout.start.both, 0.0, 0.0, setpoint.kind)
            return Word(layout.safe(inputs), 0.0, 0.0, ControlMode.VELOCITY)
        if self.restricted(unit):  # an error reset still goes: admitted, so it is sent
            kept = layout.safe(inputs) | inputs & layout.error_reset
            return Word(kept, 0.0, 0.0, ControlMode.VELOCITY)
        if self.estop is not None:  # stop category 1, first step: the drive's ramp to zero
            return Word(inputs & ~layout.start.both, 0.0, 0.0, setpoint.kind)
        if not (owned and ready):  # no present owner, or a robot not whole: zero
            return Word(inputs, 0.0, 0.0, setpoint.kind)
        return Word(inputs, setpoint.ay, setpoint.bx, setpoint.kind)


__all__ = [
    "ESTOP_POWER_OFF_S",
    "STOPPED_BELOW",
    "EStop",
    "MotionGate",
    "Word",
    "idle_axes",
    "moving_switches",
]
