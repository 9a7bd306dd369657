"""The fake-clock rig: a supervisor and simulated drives on one :class:`Timeline`."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from abh3_supervisor.config import Config
from abh3_supervisor.config.model import ControlMode, VelocityModel
from abh3_supervisor.core.commands import CurrentCommand, VelocityCommand
from abh3_supervisor.core.inputs import (
    DEFAULT_TIMEOUT,
    InputCommand,
    InputSource,
    Twist,
    VelocityYX,
)
from abh3_supervisor.core.kinematics import ab_to_yx, yx_to_ab
from abh3_supervisor.core.supervisor import Notice, Supervisor, SupervisorEvent
from abh3_supervisor.errors import CommandError
from abh3_supervisor.simulator import SimBus
from abh3_supervisor.simulator.timeline import Timeline

TWO_UNITS = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50, broadcast: {mask: 0x7f, rate_hz: 14}}
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor, command_rate_hz: 50,
     broadcast: {mask: 0x0f, rate_hz: 8}}
"""


class Rig:
    """A supervisor and simulated drives on one fake-clock bus."""

    def __init__(
        self, config: Config, bitrate: int | None = None, *, whole_robots: bool = True
    ) -> None:
        self.timeline = Timeline(bitrate)
        self.config = config
        self.sup = Supervisor(config, clock=self.timeline.clock, whole_robots=whole_robots)
        bus = next(iter(config.buses))
        sim_cfg = config.buses[bus].simulate
        assert sim_cfg is not None
        self.sim = SimBus.for_units(
            config.units_on(bus), sim_cfg, 0.0, robots=config.robots.values()
        )
        self.scheduler = self.sup.schedulers[bus]
        self.timeline.add(self.scheduler, after_step=lambda: self.sup.dispatch(bus))
        self.timeline.add(self.sim)
        self.timeline.add(Clockwork(self.sup))
        self.events: list[object] = []
        self.sup.subscribe(self.events.append)
        for unit in config.units:  # the test is the operator: its API commands stand
            self.sup.arbiter.add(_TestSource(f"api:{unit}", (unit,), timeout=math.inf))

    def run(self, seconds: float) -> None:
        self.timeline.run_until(self.timeline.now + seconds)

    def drive(self, unit: str):  # type: ignore[no-untyped-def]
        return self.sim.drives[self.config.units[unit].abh3_id]

    def own(self, unit: str) -> str:
        """A source present for the whole test that owns ``unit``'s motion (pass it as
        ``source=``), besides the rig's operator ``api:<unit>``."""
        return present(self.sup, unit)


def present(sup: Supervisor, unit: str) -> str:
    """Register a test's input source for ``unit`` that never lapses; its name."""
    name = f"test:{unit}"
    if name not in sup.arbiter.sources:
        sup.arbiter.add(_TestSource(name, (unit,), timeout=math.inf))
    return name


def streamed(sup: Supervisor, unit: str) -> str:
    """Register a test's *streamed* input source for ``unit``: its commands are fresh for
    0.5 s (``DEFAULT_TIMEOUT``), as a joystick's; silence is zero. Its name."""
    name = f"stream:{unit}"
    if name not in sup.arbiter.sources:
        sup.arbiter.add(_TestSource(name, (unit,), timeout=DEFAULT_TIMEOUT))
    return name


class _TestSource(InputSource):
    def start(self, feed: object) -> None:
        pass

    def stop(self) -> None:
        pass


class Deaf:
    """A Timeline node that hears nothing: it only acts when polled."""

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        pass

    def on_send_failed(self, arbitration_id: int) -> None:
        pass

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        pass


class Clockwork(Deaf):
    """The runtime's timers on the fake clock: the arbitration expired at its deadline
    (``Runtime._arbitrate``), the supervisor's ``call_at`` calls run when due (the
    e-stop's power-off deadline)."""

    def __init__(self, sup: Supervisor) -> None:
        self.sup = sup
        self.calls: list[tuple[float, Callable[[], None]]] = []
        sup.call_at = self.at

    def at(self, when: float, fn: Callable[[], None]) -> None:
        self.calls.append((when, fn))

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        due = [fn for when, fn in self.calls if when <= now]
        self.calls = [(when, fn) for when, fn in self.calls if when > now]
        for fn in due:
            fn()
        if now >= self.sup.arbiter.next_deadline():
            self.sup.arbiter.poll(now)
        return []

    def next_deadline(self) -> float:
        return min([self.sup.arbiter.next_deadline(), *(when for when, _ in self.calls)])


# ------------------------------------------------------------ motion, as an input gives it


@dataclass(frozen=True, slots=True)
class Taken:
    """What a unit has after a submission: its setpoint (AY/BX in its model), and whether
    the values were limited on the way (the unit's, its robot's or the wire's limits)."""

    ay: float
    bx: float
    clamped: bool


def submit(sup: Supervisor, name: str, command: InputCommand, source: str | None = None) -> Taken:
    """``command`` as the input source ``source``'s, through the one input path: the
    arbitration (core/inputs.py), on the loop's side, as the control socket's ``velocity``/
    ``twist``/``current`` give it — a refusal first said by ``Supervisor.refuse_motion``
    (e-stop, held, a parameter write, a monitor, the robot not whole, the wrong mode), then
    the source's submission, which the arbitration applies or refuses (said as a notice).

    ``name``: a unit, or for a twist a robot or one of its units (the result is that
    unit's, the robot's first unit's when a robot is named). ``source``: default the rig's
    operator ``api:<unit>``; registered, present for the whole test, if absent. Raises
    :class:`CommandError` when the unit did not take the command: the refusal's reason."""
    if isinstance(command, Twist):
        robot = sup.robot(name)
        unit = name if name in robot.units else robot.units[0]
        units = robot.units
    else:
        unit, units = sup.unit(name).name, (name,)
    values = _values(command)
    if any(values):  # as the control socket refuses in its answer, not only in a notice
        kind = ControlMode.CURRENT if isinstance(command, CurrentCommand) else ControlMode.VELOCITY
        for each in units:
            sup.refuse_motion(each, kind)
    owner = source if source is not None else f"api:{unit}"
    if owner not in sup.arbiter.sources:
        sup.arbiter.add(_TestSource(owner, (unit,), timeout=math.inf))
    if sup.arbiter.closed:  # as the feed: inputs stopped, nothing may command motion
        raise CommandError("the supervisor is stopping: commands are refused")
    said: list[str] = []

    def hear(event: SupervisorEvent) -> None:
        if isinstance(event, Notice):
            said.append(event.message)

    sup.subscribe(hear)
    try:
        sup.arbiter.submit(owner, command, sup.clock())
    finally:
        sup.unsubscribe(hear)
    setpoint = sup.units[unit].setpoint
    if any(values) and setpoint.owner != owner:
        refused = f"input {owner} refused: "
        why = next((m[len(refused) :] for m in said if m.startswith(refused)), None)
        holder = sup.arbiter.owner(unit)
        raise CommandError(
            why
            if why is not None
            else f"unit '{unit}' is driven by input {holder}: not applied"
            if holder is not None and holder != owner
            else f"unit '{unit}' did not take the command (refused within the last second)"
        )
    if isinstance(command, Twist):
        plan = sup.robots[sup.robot(name).name].last
        clamped = plan is not None and plan.note is not None
    else:
        asked = _asked(sup, unit, command)
        clamped = asked is not None and (setpoint.ay, setpoint.bx) != asked
    return Taken(setpoint.ay, setpoint.bx, clamped)


def set_velocity(
    sup: Supervisor, unit: str, ay: float, bx: float, source: str | None = None
) -> Taken:
    """AY/BX velocities as the drive reads them [min⁻¹] (the feed's ``velocity``)."""
    return submit(sup, unit, VelocityCommand(ay, bx), source)


def set_velocity_yx(
    sup: Supervisor, unit: str, y: float, x: float, source: str | None = None
) -> Taken:
    """Travel/turn velocities [min⁻¹] (the feed's ``velocity_yx``)."""
    return submit(sup, unit, VelocityYX(y, x), source)


def set_velocity_ab(
    sup: Supervisor, unit: str, a: float, b: float, source: str | None = None
) -> Taken:
    """Motor-axis velocities A/B [min⁻¹] (the feed's ``velocity_ab``)."""
    return submit(sup, unit, VelocityYX(*ab_to_yx(a, b)), source)


def set_current(
    sup: Supervisor, unit: str, ay: float, bx: float, source: str | None = None
) -> Taken:
    """Current commands [%] (the feed's ``current``); torque mode on both axes."""
    return submit(sup, unit, CurrentCommand(ay, bx), source)


def set_twist(
    sup: Supervisor, name: str, linear_x: float, angular_z: float, source: str | None = None
) -> Taken:
    """A robot twist [m/s, rad/s] to the robot ``name`` or the robot of the unit ``name``:
    every drive of it at once (the feed's ``twist``)."""
    return submit(sup, name, Twist(linear_x, angular_z), source)


def _values(command: InputCommand) -> tuple[float, ...]:
    if isinstance(command, Twist):
        return command.linear_x, command.angular_z
    if isinstance(command, VelocityYX):
        return command.y, command.x
    if isinstance(command, VelocityCommand | CurrentCommand):
        return command.ay, command.bx
    return ()


def _asked(sup: Supervisor, unit: str, command: InputCommand) -> tuple[float, float] | None:
    """The AY/BX ``command`` asks of ``unit`` in its model, before any limit."""
    if isinstance(command, VelocityCommand | CurrentCommand):
        return command.ay, command.bx
    if isinstance(command, VelocityYX):
        if sup.units[unit].cfg.velocity_model is VelocityModel.MOTOR:
            return yx_to_ab(command.y, command.x)
        return command.y, command.x
    return None
