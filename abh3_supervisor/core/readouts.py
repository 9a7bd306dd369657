"""What every readout says alike: which axes a unit's velocities are, the servo and start
its drive reports, and the error/alarm bits that are normal for its role.

``abh3 status``, the TUI, ``/diagnostics`` and the event log all read a unit through these
few functions, so they label it in the same words. Pure: no I/O, no state.
"""

from __future__ import annotations

from dataclasses import dataclass

from abh3_supervisor.config.model import Role, VelocityModel
from abh3_supervisor.core.state import UnitState
from abh3_supervisor.protocol import flags, frames

MONITOR_NOTE = "no commands (monitor)"
REPORT_OLD_S = 1.0  # a control word older than this is said to be old


# ---------------------------------------------------------------- axes


def axes(model: VelocityModel) -> str:
    """What a unit's AY/BX fields are: ``Y/X`` (travel/turn) or ``A/B`` (the motors)."""
    return "Y/X" if model is VelocityModel.TRAVEL else "A/B"


def other_axes(model: VelocityModel) -> str:
    """The other model's pair, shown beside the unit's own."""
    return "A/B" if model is VelocityModel.TRAVEL else "Y/X"


# ---------------------------------------------------------------- error/alarm bits


def normal_faults(role: Role) -> int:
    """Error/alarm bits that are normal for a unit of ``role``: shown as a note, not a fault.

    A drive sets CAN_COMM_ERROR (bit 22, alarm then error word) when no command reaches
    it for its command-zero and CAN error timeouts (parameters 0x4117, 0x4118). A monitor
    unit never commands its drive, so there the bit says "no commands", which is what a
    monitor means. On a commanding unit it is a real error: the keepalive is late.
    """
    return flags.CAN_COMM_ERROR if role is Role.MONITOR else 0


def fault_note(role: Role, bit: flags.FlagBit) -> str | None:
    """What to show instead of an error/alarm bit that is normal for ``role``, else None."""
    return MONITOR_NOTE if bit.mask & normal_faults(role) else None


@dataclass(frozen=True, slots=True)
class Faults:
    """An error or alarm word read for a unit's role."""

    bits: tuple[flags.FlagBit, ...]  # set bits that are faults
    normal: tuple[flags.FlagBit, ...]  # set bits normal for the role (see normal_faults)

    @property
    def names(self) -> list[str]:
        return [b.name for b in self.bits]

    @property
    def notes(self) -> list[str]:
        """What the normal bits say, once."""
        return [MONITOR_NOTE] if self.normal else []

    def labelled(self) -> list[str]:
        """Every set bit by name, a normal one with its note: ``CAN_COMM_ERROR (no commands
        (monitor))``."""
        return [b.name for b in self.bits] + [f"{b.name} ({MONITOR_NOTE})" for b in self.normal]


def read_faults(role: Role, value: int | None) -> Faults:
    """The set bits of an error or alarm word, faults apart from what is normal for ``role``."""
    normal = normal_faults(role)
    bits = tuple(flags.FAULT.set_bits(value or 0))
    return Faults(
        tuple(b for b in bits if not b.mask & normal), tuple(b for b in bits if b.mask & normal)
    )


# ---------------------------------------------------------------- servo and start


@dataclass(frozen=True, slots=True)
class Reported:
    """Servo and start per axis (A/Y, B/X) as the drive last reported them, at ``t``."""

    t: float
    servo: tuple[bool, bool]
    start: tuple[bool, bool]


def switches(layout: flags.Layout, control: int, t: float) -> Reported:
    """Servo and start read from a control word in the unit's layout."""
    return Reported(
        t,
        (bool(control & layout.servo.ay), bool(control & layout.servo.bx)),
        (bool(control & layout.start.ay), bool(control & layout.start.bx)),
    )


def control_reported_at(unit: UnitState) -> float | None:
    """When the drive last reported its control word: the 2023 DP0 reply or the 2021
    broadcast 1 (None before it has)."""
    times = []
    if unit.feedback is not None and unit.feedback.control is not None:
        times.append(unit.feedback.t)
    brd1 = unit.status.get(1)
    if brd1 is not None and isinstance(brd1[1], frames.Brd1) and brd1[1].control is not None:
        times.append(brd1[0])
    return max(times, default=None)
