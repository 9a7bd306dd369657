"""What an operator's key will do, decided from the state the drive reports: pure logic.

A toggle acts on what the drive reports (its control word), not on what was last
commanded, and a question says what will happen. A key that cannot act (e-stop latched,
unit offline, monitor unit, errors present) says so at once and asks nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

from abh3_supervisor.clients.mirror import Mirror, UnitView
from abh3_supervisor.clients.tui.model import axes, reported, spoken, unit_of
from abh3_supervisor.config.model import Role, VelocityModel
from abh3_supervisor.core.robot import RobotConfig, wheel_axes
from abh3_supervisor.core.twist_limits import fastest_twist
from abh3_supervisor.protocol import flags

SWITCHES = ("SERVO", "START", "BRAKE", "TORQUE")


@dataclass(frozen=True)
class Plan:
    """Commands to send in order, after ``question`` is answered yes (None: at once);
    or, when ``commands`` is empty, only ``say`` (the reason nothing is done)."""

    commands: tuple[str, ...] = ()
    question: str | None = None
    say: str = ""


def refusal(sup: Mirror, name: str) -> str | None:
    """Why no command can reach this unit now, or None."""
    unit = sup.units[name]
    if unit.cfg.role is not Role.COMMAND:
        return f"{name} is a monitor unit (role: monitor): it takes no commands"
    if sup.stopping:
        return "the supervisor is stopping: commands are refused"
    if unit.online is False:
        return f"{name} is OFFLINE: no command can reach it (f answers again if simulated)"
    if unit.other_generation:
        return f"{name} is HELD: {unit.other_generation}"
    return None


def estop_note() -> str:
    return "EMERGENCY STOP latched: nothing may move until E (shift+e) clears it"


def mask(unit: UnitView, what: str) -> int:
    lay = unit.layout
    return {
        "SERVO": lay.servo.both,
        "START": lay.start.both,
        "BRAKE": lay.brake_release,
        "TORQUE": lay.torque.both,
    }[what]


def motion(unit: UnitView) -> str:
    sp = unit.setpoint
    return f"{spoken(axes(unit), sp.ay, sp.bx)} {unit_of(unit)}"


def _moving(unit: UnitView) -> bool:
    return bool(unit.setpoint.ay or unit.setpoint.bx)


def _consequence(unit: UnitView, what: str, control: int | None) -> str:
    """What switching ``what`` on will do, in the drive's reported state."""
    lay = unit.layout
    servo_on = bool((unit.inputs if control is None else control) & lay.servo.both)
    start_on = bool(unit.inputs & lay.start.both)
    if what == "SERVO":
        if start_on and _moving(unit):
            return f"START is on and the setpoint is {motion(unit)}: THE MOTOR WILL MOVE."
        if start_on:
            return "START is on, the setpoint is zero: the motor is held at zero speed."
        return "START is off: the motor is energised and held still."
    if what == "START":
        if servo_on and _moving(unit):
            return f"the servo is on and the setpoint is {motion(unit)}: THE MOTOR WILL MOVE."
        if servo_on:
            return "the servo is on, the setpoint is zero: nothing moves until a command."
        return "the servo is off: nothing moves until SERVO is on."
    if what == "BRAKE":
        return "the brake is released: with the servo off, a load can turn the axes freely."
    return "current (torque) mode: the command is zeroed and then read as % current."


def toggle(sup: Mirror, name: str, what: str) -> Plan:
    """``v`` ``s`` ``b`` ``T``: the switch as the drive reports it, flipped."""
    unit = sup.units[name]
    if (why := refusal(sup, name)) is not None:
        return Plan(say=why)
    bits = mask(unit, what)
    control = reported(unit)
    shown_on = bool((unit.inputs if control is None else control) & bits)
    commanded_on = bool(unit.inputs & bits)
    note = " (the drive has not reported it yet)" if control is None else ""
    if shown_on:  # switching off never moves a motor: at once
        return Plan((f"{what} OFF OFF",), say=f"{what} OFF on {name}{note}")
    if what == "START" and sup.estop:
        return Plan(say=estop_note())
    errors = flags.FAULT.names(unit.words.get("error", 0))
    if what == "SERVO" and errors:
        return Plan(
            say=f"{name} reports errors ({' '.join(errors)}): the servo stays off until "
            "r (error reset) clears them"
        )
    head = f"{what} ON on {name}: {_consequence(unit, what, control)}"
    if commanded_on:  # commanded on, reported off: the drive holds it off
        why = (
            "the drive reports it off although it is commanded on (after an error reset "
            "the drive keeps the servo off until it sees SERVO off)"
        )
        return Plan(
            (f"{what} OFF OFF", f"{what} ON ON"),
            question=f"{head}\n\n{why}. Send {what} OFF, then ON?{note}",
        )
    return Plan((f"{what} ON ON",), question=f"{head}\n\nSend {what} ON ON?{note}")


def reset(sup: Mirror, name: str) -> Plan:
    """``r``: a rising edge of ERROR RESET, then SERVO off too: the drive keeps the servo off
    after a reset until it sees SERVO off, so the command matches what it does."""
    if (why := refusal(sup, name)) is not None:
        return Plan(say=why)
    errors = " ".join(flags.FAULT.names(sup.units[name].words.get("error", 0))) or "none"
    return Plan(
        ("RESET ON ON", "RESET OFF OFF", "SERVO OFF OFF"),
        question=(
            f"Error reset on {name}? Errors now: {errors}.\n\nThe servo goes off (the drive "
            "keeps it off after a reset until it sees SERVO off, so SERVO OFF is sent too); "
            "v switches it on again, asking first."
        ),
    )


def drive_refusal(sup: Mirror, names: tuple[str, ...], moving: bool) -> str | None:
    """Why an arrow key cannot drive these units now, or None."""
    if moving and sup.estop:
        return estop_note()
    if not names:
        return "no unit to drive: every unit is a monitor unit"
    for name in names:
        if (why := refusal(sup, name)) is not None:
            return why
    return None


SWITCH_KEYS = {"SERVO": "v", "START": "s"}


def stillness(sup: Mirror, names: tuple[str, ...]) -> str | None:
    """Why a twist to these units moves nothing: SERVO or START off, judged from the control
    word the drive reports (from the commanded one until it has reported); or None."""
    parts: list[str] = []
    off_anywhere: set[str] = set()
    for name in names:
        unit = sup.units[name]
        control = reported(unit)
        word = unit.inputs if control is None else control
        # the axes that drive a wheel: one that drives none is never switched on
        cfg = sup.config.units[name]
        used = wheel_axes(
            sup.config.robot_of(name), name, cfg.velocity_model is VelocityModel.MOTOR
        )
        lay = unit.layout
        need = {
            "SERVO": sum(lay.servo.of(a) for a in used),
            "START": sum(lay.start.of(a) for a in used),
        }
        off = [w for w in SWITCH_KEYS if word & need[w] != need[w]]
        if not off:
            continue
        off_anywhere.update(off)
        held = 0 if control is None else unit.inputs & ~control  # commanded, reported off
        said = [f"{w} off" + (" (commanded on)" if held & need[w] else "") for w in off]
        unheard = " (as commanded: the drive has not reported yet)" if control is None else ""
        parts.append(f"{name}: {', '.join(said)}{unheard}")
    if not parts:
        return None
    how = ", ".join(f"{k} to switch {w} on" for w, k in SWITCH_KEYS.items() if w in off_anywhere)
    return f"{'; '.join(parts)} — nothing moves ({how})"


def robots_of(sup: Mirror, names: tuple[str, ...]) -> tuple[RobotConfig, ...]:
    """The robots whose drives ``names`` are, in order, each once (a monitor unit drives
    none): what the arrows drive, each robot as a whole."""
    found = (sup.config.robot_of(name) for name in names)
    return tuple({r.name: r for r in found if r is not None}.values())


def robot_units(robots: tuple[RobotConfig, ...]) -> tuple[str, ...]:
    return tuple(u for robot in robots for u in robot.units)


def arrows_drive(robots: tuple[RobotConfig, ...]) -> str:
    """What the arrows drive, as said: a one-drive robot by its unit, a declared robot by
    its name and its drives (``rover (left, right)``)."""
    if not robots:
        return "no robot"
    return ", ".join(r.name if r.implicit else f"{r.name} ({', '.join(r.units)})" for r in robots)


def speed_caps(sup: Mirror, names: tuple[str, ...]) -> tuple[float, float]:
    """The fastest twist the arrow keys may ask of the robots of these units within their
    limits (the robot's own, each wheel's axis, each drive's velocity limit): (linear m/s,
    angular rad/s); the arrows give one or the other, never both."""
    speed = turn = float("inf")
    for robot in robots_of(sup, names):
        fastest = fastest_twist(robot, sup.config.units)
        speed, turn = min(speed, fastest[0]), min(turn, fastest[1])
    return speed, turn
