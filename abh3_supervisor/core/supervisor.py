"""The Supervisor API: the one interface the CLI, the TUI and every plugin use.

It owns one :class:`BusScheduler` per bus and every unit's state. Setpoints are encoded
once when set (never per cycle) and handed to the scheduler; scheduler events update the
state and reach observers. Everything here runs on the event loop's thread.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass

from abh3_supervisor.config.model import Config, ControlMode, Role, VelocityModel
from abh3_supervisor.core import commands
from abh3_supervisor.core.commands import (
    Command,
    CurrentCommand,
    InputChange,
    SelectCommand,
    SwitchCommand,
    VelocityCommand,
)
from abh3_supervisor.core.kinematics import ab_to_yx, twist_to_yx, yx_to_ab
from abh3_supervisor.core.state import Feedback, Setpoint, UnitState
from abh3_supervisor.core.text import clean
from abh3_supervisor.core.throttle import Throttle, held_note
from abh3_supervisor.core.verify import Verification
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import frames
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY, Scale
from abh3_supervisor.scheduler.bus_health import BusHealth, BusState
from abh3_supervisor.scheduler.core import (
    BusScheduler,
    Event,
    FeedbackEvent,
    GapEvent,
    HealthEvent,
    MalformedEvent,
    StatusEvent,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class FlagChange:
    unit: str
    t: float
    word: str  # a key of the unit's Layout.words: "error", "alarm", "control", "io", …
    old: int | None
    new: int

    @property
    def set_bits(self) -> int:
        return self.new & ~(self.old or 0)

    @property
    def cleared_bits(self) -> int:
        return (self.old or 0) & ~self.new


@dataclass(frozen=True, slots=True)
class Notice:
    """Something an operator should read: clamping, e-stop, model mismatch, plugin errors."""

    unit: str | None
    t: float
    level: int  # a logging level
    message: str


@dataclass(frozen=True, slots=True)
class OperatorAction:
    """Something an operator did (a key, a command line, an answer to a question): the
    audit trail, logged by the TUI and headless alike."""

    unit: str | None
    t: float
    source: str  # who acted: "tui", "signal", an input's name
    action: str


SupervisorEvent = Event | FlagChange | Notice | OperatorAction
Observer = Callable[[SupervisorEvent], None]


@dataclass(frozen=True, slots=True)
class SetResult:
    ay: float
    bx: float
    clamped: bool


class Supervisor:
    def __init__(self, config: Config, clock: Callable[[], float]) -> None:
        self.config = config
        self.clock = clock
        now = clock()
        self.units = {name: UnitState.initial(cfg) for name, cfg in config.units.items()}
        self.schedulers = {bus: BusScheduler(config.units_on(bus), now) for bus in config.buses}
        # what each bus's interface reports of itself (bus-off, error-passive, …)
        self.bus_health = {bus: BusHealth(bus) for bus in config.buses}
        self._observers: list[Observer] = []
        # unit, or (unit, broadcast packet) → (requests sent since, future) awaiting a reply;
        # DP0 replies are keyed by the unit alone: no key is built on the bus path
        self._waiters: dict[Hashable, list[tuple[float, asyncio.Future[bool]]]] = {}
        self.estop = False
        self.stopping = False  # set by safe_state(): every later command is refused
        # per bus: step the scheduler now (set by the runtime; absent on a fake clock)
        self.wakers: dict[str, Callable[[], None]] = {}
        self._throttle = Throttle(1.0)
        for unit in self.units.values():
            self._push(unit)

    # ------------------------------------------------------------ observing

    def subscribe(self, observer: Observer) -> None:
        self._observers.append(observer)

    def unsubscribe(self, observer: Observer) -> None:
        self._observers.remove(observer)

    def _emit(self, event: SupervisorEvent) -> None:
        for observer in list(self._observers):
            try:
                observer(event)
            except Exception:  # an observer's bug must never stop the bus path
                log.exception("observer %r failed on %s", observer, type(event).__name__)

    def notice(self, unit: str | None, level: int, message: str) -> None:
        self._emit(Notice(unit, self.clock(), level, message))

    def audit(self, source: str, unit: str | None, action: str) -> None:
        """Record an operator's action for every observer (the event logs, plugins); the
        text may come from a client, so it is escaped and capped (no forged lines)."""
        self._emit(OperatorAction(unit, self.clock(), clean(source), clean(action)))

    def dispatch(self, bus: str) -> None:
        """Apply the events one bus's scheduler recorded (called after each pump step)."""
        for event in self.schedulers[bus].drain_events():
            self._apply(event)
            self._emit(event)
        health = self.bus_health[bus]
        for change in health.drain() if health.changes else ():
            bad = change.new is not BusState.OK
            state = change.new.upper() if bad else f"recovered from {change.old}"
            level = logging.ERROR if change.new is BusState.BUS_OFF else logging.WARNING
            self._emit(
                Notice(
                    None,
                    change.t,
                    level if bad else logging.INFO,
                    f"bus {bus}: {state}: {change.detail}",
                )
            )

    def _apply(self, event: Event) -> None:
        unit = self.units[event.unit]
        if isinstance(event, FeedbackEvent):
            if isinstance(event.reply, frames.Unknown):
                return
            unit.feedback = Feedback.from_reply(event.t, event.reply, unit.cfg.velocity_model)
            if unit.feedback.control is not None:
                self._word(unit, event.t, "control", unit.feedback.control)
            if event.sent_at is not None:
                self._wake(unit.name, event.sent_at)
        elif isinstance(event, StatusEvent):
            if isinstance(event.record, frames.Unknown):
                return
            unit.status[event.packet] = (event.t, event.record)
            record = event.record
            if isinstance(record, frames.Brd0):
                self._word(unit, event.t, "error", record.error)
                self._word(unit, event.t, "alarm", record.alarm)
            elif isinstance(record, frames.Brd1):
                self._word(unit, event.t, "io", record.io)
                if record.control is not None:
                    self._word(unit, event.t, "control", record.control)
                if record.inputs is not None:  # 2023: the inputs as the drive sees them
                    self._word(unit, event.t, "drive_inputs", record.inputs)
            if event.sent_at is not None:
                self._wake((unit.name, event.packet), event.sent_at)
        elif isinstance(event, HealthEvent):
            unit.online = event.online
            if not event.online and unit.cfg.role is Role.COMMAND:
                # a lost drive stops itself (command-zero timeout); do not resume it moving
                # on return with a stale setpoint: its command drops to zero
                self._zero(unit)
        elif isinstance(event, GapEvent):
            self._gap(unit, event)
        elif isinstance(event, MalformedEvent):
            held = self._throttle.allow((unit.name, event.kind), event.t)
            if held is not None:
                self.notice(
                    unit.name,
                    logging.WARNING,
                    f"malformed {event.kind} ignored: {event.reason}{held_note(held)}",
                )

    def _gap(self, unit: UnitState, event: GapEvent) -> None:
        """The drive stopped itself for want of commands: it must not restart on its own."""
        ms = unit.cfg.drive_timeout_ms
        if event.started:
            moving = bool(unit.setpoint.ay or unit.setpoint.bx)
            self._zero(unit)
            self.notice(
                unit.name,
                logging.WARNING,
                f"no exchange completed for {ms} ms (drive_timeout_ms): the drive has stopped "
                f"on its command-zero timeout; command "
                + ("set to zero: nothing moves until a new command" if moving else "stays zero"),
            )
        else:
            self.notice(unit.name, logging.INFO, "exchanges again after the gap; command zero")

    def _word(self, unit: UnitState, t: float, word: str, value: int) -> None:
        old = unit.words.get(word)
        if old == value:
            return
        unit.words[word] = value
        if word == "control":
            model_bit = unit.layout.travel_model
            travel = bool(value & model_bit)
            expected = unit.cfg.velocity_model is VelocityModel.TRAVEL
            if travel != expected and (old is None or bool(old & model_bit) != travel):
                self.notice(
                    unit.name,
                    logging.WARNING,
                    f"drive reports the {'travel' if travel else 'motor'} model but the "
                    f"configuration says velocity_model: {unit.cfg.velocity_model}",
                )
        self._emit(FlagChange(unit.name, t, word, old, value))

    # ------------------------------------------------------------ commanding

    def unit(self, name: str) -> UnitState:
        try:
            return self.units[name]
        except KeyError:
            raise CommandError(f"no unit named '{name}' (units: {', '.join(self.units)})") from None

    def _commandable(self, name: str) -> UnitState:
        unit = self.unit(name)
        if self.stopping:
            raise CommandError("the supervisor is stopping: commands are refused")
        if unit.cfg.role is not Role.COMMAND:
            raise CommandError(f"unit '{name}' is configured role: monitor and takes no commands")
        return unit

    def set_velocity_ab(self, name: str, a: float, b: float) -> SetResult:
        """Motor-axis velocities [min⁻¹], converted to the drive's model."""
        unit = self._commandable(name)
        _finite(a, b)
        if unit.cfg.velocity_model is VelocityModel.TRAVEL:
            return self._set(unit, *ab_to_yx(a, b), ControlMode.VELOCITY)
        return self._set(unit, a, b, ControlMode.VELOCITY)

    def set_velocity_yx(self, name: str, y: float, x: float) -> SetResult:
        """Travel/turn velocities [min⁻¹], converted to the drive's model."""
        unit = self._commandable(name)
        _finite(y, x)
        if unit.cfg.velocity_model is VelocityModel.MOTOR:
            return self._set(unit, *yx_to_ab(y, x), ControlMode.VELOCITY)
        return self._set(unit, y, x, ControlMode.VELOCITY)

    def set_velocity(self, name: str, ay: float, bx: float) -> SetResult:
        """AY/BX velocities as the drive reads them (its configured model) [min⁻¹]."""
        unit = self._commandable(name)
        _finite(ay, bx)
        return self._set(unit, ay, bx, ControlMode.VELOCITY)

    def set_twist(self, name: str, linear_x: float, angular_z: float) -> SetResult:
        """Robot twist [m/s, rad/s] through the unit's geometry."""
        unit = self._commandable(name)
        _finite(linear_x, angular_z)
        return self.set_velocity_yx(name, *twist_to_yx(linear_x, angular_z, unit.cfg.geometry))

    def set_current(self, name: str, ay: float, bx: float) -> SetResult:
        """Current commands [%]; the unit must be in torque mode on both axes."""
        unit = self._commandable(name)
        _finite(ay, bx)
        return self._set(unit, ay, bx, ControlMode.CURRENT)

    def zero(self, name: str) -> None:
        """Zero command in the unit's current mode (velocity or current); flags unchanged."""
        unit = self._commandable(name)
        self._zero(unit)

    def set_inputs(self, name: str, data: int, mask: int) -> None:
        """Change the input bits selected by ``mask`` to those of ``data`` (seed inp_data)."""
        unit = self._commandable(name)
        layout = unit.layout
        if undefined := layout.undefined(data & mask):
            raise CommandError(
                f"bits 0x{undefined:08X} are not defined in the {layout.generation} input "
                f"word of unit '{name}': refused, nothing sent"
            )
        new = (unit.inputs & ~mask | data & mask) & 0xFFFFFFFF
        if self.estop and new & ~unit.inputs & layout.start.both:
            raise CommandError("emergency stop is latched: clear it before START")
        held = unit.verify.holds()  # verify: refuse (core/verify.py)
        # held: the idle word only — nothing may be switched on (a brake released with the
        # servo off lets a load fall) but data select, which picks a table, and error reset
        harmless = layout.select_mask | layout.error_reset
        if held and new & ~unit.inputs & ~harmless:
            raise CommandError(f"unit '{name}' is held at its idle word: {held}")
        torque = new & layout.torque.both
        kind = unit.setpoint.kind
        if torque != unit.inputs & layout.torque.both:
            # the meaning of the command fields changes: never reinterpret an old value
            kind = ControlMode.CURRENT if torque else ControlMode.VELOCITY
            unit.setpoint = Setpoint(kind=kind)
        unit.inputs = new
        self._push(unit)

    def _check(self, unit: UnitState, ay: float, bx: float, kind: ControlMode) -> None:
        """Refuse what the unit cannot take now: motion under the e-stop, the wrong mode."""
        if self.estop and (ay or bx):
            raise CommandError("emergency stop is latched: clear it before commanding motion")
        both = unit.layout.torque.both
        torque = unit.inputs & both
        want = both if kind is ControlMode.CURRENT else 0
        if torque != want:
            mode = {0: "velocity", both: "current"}.get(torque, "mixed")
            raise CommandError(
                f"unit '{unit.name}' is in {mode} mode; a {kind} command needs "
                f"TORQUE {'ON ON' if want else 'OFF OFF'} first"
            )

    def admit(self, name: str, command: VelocityCommand | CurrentCommand) -> str | None:
        """Check a ``VEL``/``CUR`` as it would be applied now, without applying it: raise
        :class:`CommandError` if refused; the clamp note if it would be clamped."""
        unit = self._commandable(name)
        _finite(command.ay, command.bx)
        kind = ControlMode.CURRENT if isinstance(command, CurrentCommand) else ControlMode.VELOCITY
        self._check(unit, command.ay, command.bx, kind)
        return _limited(unit, command.ay, command.bx, kind)[2]

    def _set(self, unit: UnitState, ay: float, bx: float, kind: ControlMode) -> SetResult:
        self._check(unit, ay, bx, kind)
        ay, bx, note = _limited(unit, ay, bx, kind)
        if note is not None:  # a stream beyond the limit (a joystick) says it once a second
            held = self._throttle.allow((unit.name, "clamped"), self.clock())
            if held is not None:
                self.notice(unit.name, logging.WARNING, note + held_note(held))
        self._store(unit, Setpoint(ay, bx, kind))
        return SetResult(unit.setpoint.ay, unit.setpoint.bx, note is not None)

    def _store(self, unit: UnitState, setpoint: Setpoint) -> None:
        unit.setpoint = setpoint
        self._push(unit)

    def _zero(self, unit: UnitState) -> None:
        """Zero command in the unit's current mode (velocity or current)."""
        self._store(unit, Setpoint(kind=unit.setpoint.kind))

    def _push(self, unit: UnitState) -> None:
        if unit.cfg.role is not Role.COMMAND:
            return
        scale = CURRENT if unit.setpoint.kind is ControlMode.CURRENT else VELOCITY
        raw_ay, _ = scale.to_raw(unit.setpoint.ay)
        raw_bx, _ = scale.to_raw(unit.setpoint.bx)
        self.schedulers[unit.cfg.bus].set_payload(
            unit.name, frames.encode_dp0_command(raw_ay, raw_bx, unit.inputs)
        )

    def request_status(self, name: str, packet: int) -> None:
        """Ask the drive for broadcast ``packet`` (0-6) once, soon (seed ``brd_num``).

        Read-only, so allowed in every state; the answer arrives as a status event.
        """
        unit = self.unit(name)
        if isinstance(packet, bool) or not isinstance(packet, int) or not 0 <= packet <= 6:
            raise CommandError(f"broadcast packet {packet!r} is not 0-6")
        self.schedulers[unit.cfg.bus].request_status(name, packet)
        wake = self.wakers.get(unit.cfg.bus)
        if wake is not None:
            wake()

    async def verify_again(self, name: str) -> Verification:
        """Read the drive's CAN settings again and compare them with the file (≤ 2 s): a
        unit held by ``verify: refuse`` is released, and its start-up commands run, when
        they agree (core/verify.py). Read-only; allowed in every state."""
        from abh3_supervisor.core.verify import verify_units

        self.unit(name)
        return (await verify_units(self, [name]))[name]

    # ------------------------------------------------------------ command language

    def apply(self, name: str, command: Command) -> None:
        if isinstance(command, SwitchCommand | SelectCommand):
            change = commands.input_change(command, self.unit(name).layout)
            self.set_inputs(name, change.data, change.mask)
        elif isinstance(command, InputChange):
            self.set_inputs(name, command.data, command.mask)
        elif isinstance(command, VelocityCommand):
            self.set_velocity(name, command.ay, command.bx)
        else:
            assert isinstance(command, CurrentCommand)
            self.set_current(name, command.ay, command.bx)

    def apply_text(self, name: str, text: str) -> str:
        """Apply a command-language string now; answer as the seed's service does."""
        self.unit(name)  # an unknown unit is the caller's error, not the command's
        try:
            command = commands.parse_command(text)
        except CommandError:
            return commands.RESPONSE_INVALID
        try:
            self.apply(name, command)
        except CommandError as exc:
            return self.refusal(name, text, exc)
        return commands.RESPONSE_OK

    def refusal(self, name: str, text: str, exc: CommandError) -> str:
        """The seed's answer to a command the unit refused, and a notice saying why."""
        if self.estop:
            return commands.packet_error(commands.PACKET_ESTOP)
        self.notice(name, logging.WARNING, f"{clean(text)!r} refused: {exc}")
        return commands.RESPONSE_INVALID

    async def command(self, name: str, text: str) -> str:
        """As :meth:`apply_text`, then wait for the drive to answer a frame carrying it."""
        since = self.clock()
        response = self.apply_text(name, text)
        if response != commands.RESPONSE_OK:
            return response
        return await self.confirm(name, since)

    async def confirm(self, name: str, since: float) -> str:
        """``''`` once the drive answers a frame sent at or after ``since``; otherwise the
        seed's ``Packet Error`` with our code (no reply, or the bus refused the frame)."""
        unit = self.unit(name)
        stats = self.schedulers[unit.cfg.bus].slots[name].stats
        failures = stats.send_errors
        if await self.wait_exchange(name, since, unit.cfg.timeout_ms / 1000):
            return commands.RESPONSE_OK
        code = (
            commands.PACKET_SEND_FAILED
            if stats.send_errors > failures
            else commands.PACKET_NO_REPLY
        )
        return commands.packet_error(code)

    def expect_exchange(self, name: str, since: float) -> asyncio.Future[bool]:
        """A future set once a reply answers a request of ``name`` sent at or after ``since``.

        Registered at once (not on first await), so a reply cannot slip past it.
        """
        return self._expect(name, since)

    def expect_status(self, name: str, packet: int, since: float) -> asyncio.Future[bool]:
        """A future set once broadcast ``packet`` answers a request sent at or after
        ``since`` (ask for it with :meth:`request_status`): what the drive says *now*."""
        return self._expect((name, packet), since)

    def _expect(self, key: Hashable, since: float) -> asyncio.Future[bool]:
        future: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        waiters = self._waiters.setdefault(key, [])
        waiters.append((since, future))
        future.add_done_callback(lambda f: waiters.remove((since, f)))
        return future

    async def wait_exchange(self, name: str, since: float, timeout: float) -> bool:
        """True once a reply answers a request sent at or after ``since``; False on timeout."""
        try:
            return await asyncio.wait_for(self.expect_exchange(name, since), timeout)
        except TimeoutError:
            return False

    def _wake(self, key: Hashable, sent_at: float) -> None:
        waiters = self._waiters.get(key)
        if not waiters:  # the usual case, once per reply on the bus path: no allocation
            return
        for since, future in list(waiters):
            if sent_at >= since and not future.done():
                future.set_result(True)

    # ------------------------------------------------------------ safety

    def emergency_stop(self) -> None:
        """Zero and START off on every commanded unit; latched until cleared."""
        self.estop = True
        for unit in self.units.values():
            if unit.cfg.role is Role.COMMAND:
                unit.inputs &= ~unit.layout.start.both
                self._zero(unit)
        self.notice(None, logging.CRITICAL, "EMERGENCY STOP: all units zero, START off (latched)")

    def clear_emergency_stop(self) -> None:
        self.estop = False
        self.notice(None, logging.WARNING, "emergency stop cleared; START must be given again")

    def safe_state(self) -> None:
        """The way-out state on every unit we drove, final: zero velocity in the safe word
        (SERVO, START, brake release, torque and every other switch off; data select kept).
        """
        self.stopping = True
        for unit in self.units.values():
            if unit.cfg.role is Role.COMMAND:
                unit.inputs = unit.layout.safe(unit.inputs)
                self._store(unit, Setpoint())  # torque is off: the fields are velocities


def _limited(
    unit: UnitState, ay: float, bx: float, kind: ControlMode
) -> tuple[float, float, str | None]:
    """The values within the unit's limit and the wire's range, both axes scaled alike
    (the robot keeps its heading, only slower), and the note saying so if they changed."""
    if kind is ControlMode.VELOCITY:
        word, key, limit, wire = "VEL", "velocity", unit.cfg.limits.velocity, VELOCITY
    else:
        word, key, limit, wire = "CUR", "current", unit.cfg.limits.current, CURRENT
    scale = min([1.0, *(_bound(v, limit, wire) / abs(v) for v in (ay, bx) if v)])
    if scale >= 1.0:
        return ay, bx, None
    # the binding bound: the YAML's limit, or the wire's range where no limit is set
    if limit < wire.largest:
        why = f"limits.{key} {limit:g}"
    else:
        why = f"wire range {wire.minimum:g} … {wire.maximum:g}"
    new_ay, new_bx = ay * scale, bx * scale
    note = f"clamped: {word} {ay:g} {bx:g} → {new_ay:.6g} {new_bx:.6g} ({why})"
    return new_ay, new_bx, note


def _bound(value: float, limit: float, wire: Scale) -> float:
    """The largest magnitude ``value``'s sign may have: the limit, within the wire range
    (int16 reaches one LSB further below zero: −6553.6 min⁻¹, −327.68 %)."""
    return min(limit, wire.maximum if value > 0 else -wire.minimum)


def _finite(*values: float) -> None:
    for value in values:
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not math.isfinite(value)
        ):
            raise CommandError(f"{value!r} is not a finite number")
