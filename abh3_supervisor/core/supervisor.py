"""The Supervisor API: the one interface the CLI, the TUI and every plugin use.

It owns one :class:`BusScheduler` per bus and every unit's state. Setpoints are encoded
once when set (never per cycle) and handed to the scheduler; scheduler events update the
state and reach observers. Everything here runs on the event loop's thread.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace

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
from abh3_supervisor.core.foreign import QUIET_S, Foreign
from abh3_supervisor.core.gate import (
    ESTOP_POWER_OFF_S,
    STOPPED_BELOW,
    MotionGate,
    idle_axes,
    moving_switches,
)
from abh3_supervisor.core.inputs import (
    DEFAULT_TIMEOUT,
    CommandOutcome,
    InputArbiter,
    InputCommand,
    InputSource,
    Motion,
    Stop,
    Twist,
    VelocityYX,
    enact,
)
from abh3_supervisor.core.journal import Journal
from abh3_supervisor.core.kinematics import yx_to_ab
from abh3_supervisor.core.readiness import (
    SETTLE_S,
    DriveView,
    Unready,
    drive_unready,
    reply_generation,
    robot_unready,
    switch_names,
    switches,
)
from abh3_supervisor.core.robot import RobotConfig, axis_limits, wheel_axes
from abh3_supervisor.core.robot_motion import RobotMotion
from abh3_supervisor.core.state import Feedback, Setpoint, UnitState
from abh3_supervisor.core.text import clean
from abh3_supervisor.core.throttle import Throttle, held_note
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY, Scale
from abh3_supervisor.scheduler.bus_health import BusHealth, BusState
from abh3_supervisor.scheduler.core import (
    BusScheduler,
    Event,
    FeedbackEvent,
    ForeignEvent,
    GapEvent,
    HealthEvent,
    MalformedEvent,
    StatusEvent,
)

log = logging.getLogger(__name__)
# a 2021 drive commanded on is asked for its report (broadcast 1) at least this often
REPORT_EVERY_S = 0.1
API_SOURCE = "api"  # the source of a programmatic command: api:<unit>
STARTUP_SOURCE = "startup"  # the source of a unit's startup: motion: startup:<unit>
# a command _submit checked, and the values it checked for each target unit
_Checked = tuple[InputCommand, dict[str, tuple[float, float, ControlMode]]]


@dataclass(frozen=True, slots=True)
class FlagChange:
    """A flag word of a unit changed (hook ``abh3_flags``; public as
    ``abh3_supervisor.plugin_api.FlagChange``). Name its bits in the unit's generation with
    ``supervisor.units[change.unit].names(change.word, change.set_bits)``: every word an
    event names, ``drive_inputs`` included."""

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
    """Something an operator should read: clamping, e-stop, model mismatch, plugin errors
    (hook ``abh3_notice``; public as ``abh3_supervisor.plugin_api.Notice``)."""

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


@dataclass(frozen=True, slots=True)
class EstopChange:
    """The e-stop was latched (``latched``) or cleared; ``source`` says who latched it
    (``tui``, ``input joystick``, ``plugin watchdog: overspeed``) or cleared it."""

    t: float
    latched: bool
    source: str


@dataclass(frozen=True, slots=True)
class OwnerChange:
    """The input source whose command a unit has now changed (``None``: nobody; zero)."""

    unit: str
    t: float
    old: str | None
    new: str | None


SupervisorEvent = Event | FlagChange | Notice | OperatorAction | EstopChange | OwnerChange
Observer = Callable[[SupervisorEvent], None]


class Supervisor:
    def __init__(
        self, config: Config, clock: Callable[[], float], *, whole_robots: bool = True
    ) -> None:
        """``whole_robots``: a robot moves whole or not at all and an axis that drives no
        wheel of it is never switched on (core/readiness.py); off, each drive is decided
        alone on both axes — commissioning, which moves one motor at a time."""
        self.config = config
        self.clock = clock
        now = clock()
        self.units = {name: UnitState.initial(cfg) for name, cfg in config.units.items()}
        # a robot's units send in the same turn (one phase per robot on each bus)
        together = {u: r.name for r in config.robots.values() for u in r.units}
        self.schedulers = {
            bus: BusScheduler(config.units_on(bus), now, together, cfg.units_per_turn)
            for bus, cfg in config.buses.items()
        }
        # what each bus's interface reports of itself (bus-off, error-passive, …)
        self.bus_health = {bus: BusHealth(bus) for bus in config.buses}
        self._observers: list[Observer] = []
        # every event, written once for the watchers (core/journal.py), who are told
        # there is news once per step (the plugins' workers, the control socket's lines)
        self.journal = Journal()
        self.watchers: list[Callable[[], None]] = []
        self._told = 0  # the journal's number the watchers were last told of
        self._dispatching = False
        # unit, or (unit, broadcast packet) → (requests sent since, future) awaiting a reply;
        # DP0 replies are keyed by the unit alone: no key is built on the bus path
        self._waiters: dict[Hashable, list[tuple[float, asyncio.Future[bool]]]] = {}
        # the one place every command frame is decided (core/gate.py): e-stop, stopping,
        # parameter-write locks; the verification hold and the owner are asked of it
        self.gate = MotionGate()
        # who owns each unit's motion (core/inputs.py): every setpoint is a source's
        self.arbiter = InputArbiter(apply=self._arbitrated, clock=clock)
        # the command _submit is handing the arbitration and the values it checked for
        # each target: applied on the same stack, it is not checked again
        self._checked: _Checked | None = None
        # each robot's twist, decided once for all its drives (core/robot_motion.py)
        self.robots = {
            name: RobotMotion(robot, config.units) for name, robot in config.robots.items()
        }
        self._robot_of = {u: self.robots[r.name] for r in config.robots.values() for u in r.units}
        for robot in config.robots.values():
            for name in robot.units:
                self.units[name].axis_limits = axis_limits(robot, name)
                if whole_robots:  # commissioning tries both axes of each drive
                    motor = config.units[name].velocity_model is VelocityModel.MOTOR
                    self.units[name].wheels = wheel_axes(robot, name, motor)
        # unit → SERVO and START of its wheel axes: fixed by the file, read per reply
        self._needs = {u.name: switches(u.layout, u.wheels) for u in self.units.values()}
        # a robot moves whole or not at all (core/readiness.py): each commanded unit's
        # robot (a unit of none is a robot of its own), and whether it is ready now
        self._group: dict[str, tuple[str, tuple[str, ...]]] = {}
        for unit in self.units.values():
            if unit.cfg.role is Role.COMMAND:
                own = config.robot(unit.name) if whole_robots else None
                self._group[unit.name] = (
                    (own.name, own.units) if own is not None else (unit.name, (unit.name,))
                )
        self._ready: dict[str, bool] = {key: False for key, _ in self._group.values()}
        self.arbiter.domains = {
            u: r.units for r in config.robots.values() if len(r.units) > 1 for u in r.units
        }
        self._owners: dict[str, str | None] = {}  # as last said in an OwnerChange
        self.arbiter.watchers.append(self._owner_watch)
        self.arbiter.on_lapse = lambda name: self.notice(
            None,
            logging.WARNING,
            f"input {name} stopped proving it is alive: the motion it held dropped to zero",
        )
        # per bus: step the scheduler now (set by the runtime; absent on a fake clock)
        self.wakers: dict[str, Callable[[], None]] = {}
        self._send_now: dict[str, Callable[[str], None]] = {}  # see senders()
        # set by the runtime: call a function at a loop time (the e-stop's power-off
        # deadline, kept whatever the buses do); a fake-clock rig sets its own
        self.call_at: Callable[[float, Callable[[], None]], object] | None = None
        self._throttle = Throttle(1.0)
        self._stop_t = math.inf  # when the way out's controlled stop began
        for unit in self.units.values():
            self._push(unit)

    # ------------------------------------------------------------ observing

    def subscribe(self, observer: Observer) -> None:
        """``observer`` gets each event on the loop as it comes: for what acts on the bus
        path (the stop, commissioning); a watcher reads the journal instead."""
        self._observers = [*self._observers, observer]  # a new list: _emit loops the old

    def unsubscribe(self, observer: Observer) -> None:
        self._observers = [o for o in self._observers if o is not observer]

    def _emit(self, event: SupervisorEvent, sample: object = None) -> None:
        """Written once in the journal, for the watchers to read at their own pace; then
        to the observers on the loop — the few that act on the bus path (the stop, the
        commissioning guard) or only take note that something came (the plugins)."""
        journal = self.journal  # Journal.write, inline: once per reply
        seq = journal.seq + 1
        journal.ring[seq & journal.mask] = (seq, event, sample)
        journal.seq = seq
        for observer in self._observers:
            try:
                observer(event)
            except Exception:  # an observer's bug must never stop the bus path
                log.exception("observer %r failed on %s", observer, type(event).__name__)
        if not self._dispatching:  # a command's, an e-stop's: told at once
            self._tell()

    def _tell(self) -> None:
        """The watchers (:attr:`watchers`) that the journal has news: once per step."""
        if self._told == self.journal.seq:
            return
        self._told = self.journal.seq
        for watcher in self.watchers:
            try:
                watcher()
            except Exception:  # a watcher's bug must never stop the bus path
                log.exception("watcher %r failed", watcher)

    def _owner_watch(self, unit: str) -> None:
        """The arbiter says an owner may have changed: an event only when it did."""
        new = self.arbiter.owner(unit)
        old = self._owners.get(unit)
        if new != old:
            self._owners[unit] = new
            self._emit(OwnerChange(unit, self.clock(), old, new))

    def notice(self, unit: str | None, level: int, message: str) -> None:
        self._emit(Notice(unit, self.clock(), level, message))

    def audit(self, source: str, unit: str | None, action: str) -> None:
        """Record an operator's action for every observer (the event logs, plugins); the
        text may come from a client, so it is escaped and capped (no forged lines)."""
        self._emit(OperatorAction(unit, self.clock(), clean(source), clean(action)))

    def dispatch(self, bus: str) -> None:
        """Apply the events one bus's scheduler recorded (called after each pump step)."""
        units = self.units
        self._dispatching = True  # the watchers are told once, after the step's events
        try:
            for event in self.schedulers[bus].drain_events():
                self._apply(event)
                if type(event) is FeedbackEvent:  # the journal keeps what the reply left
                    unit = units[event.unit]
                    self._emit(event, (unit.feedback, unit.setpoint, unit.inputs))
                else:
                    self._emit(event)
        finally:
            self._dispatching = False
        self._tell()
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
            commanded = unit.cfg.role is Role.COMMAND
            changed = commanded and self._identify(unit, event)
            if self.gate.estop is not None:
                self._estop_progress(unit, event)
            if self.gate.ramping:
                self._stop_progress(unit, event)
            control = unit.feedback.control
            if control is not None:
                self._word(unit, event.t, "control", control)
                if commanded:
                    at = event.sent_at if event.sent_at is not None else event.t
                    error = bool(control & unit.layout.control.mask("ERROR"))
                    changed |= self._report(unit, control, error, at, event.t)
            elif commanded and unit.layout.brd1_inputs is None:
                self._ask_report(unit, event.t)
            if changed:
                self._readiness(unit.name)
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
                    if unit.cfg.role is Role.COMMAND:  # 2021: the drive's report is here
                        at = event.sent_at if event.sent_at is not None else event.t
                        error = bool(record.io & unit.layout.io.mask("ERROR"))
                        if self._report(unit, record.control, error, at, event.t):
                            self._readiness(unit.name)
                if record.inputs is not None:  # 2023: the inputs as the drive sees them
                    self._word(unit, event.t, "drive_inputs", record.inputs)
            if event.sent_at is not None:
                self._wake((unit.name, event.packet), event.sent_at)
        elif isinstance(event, HealthEvent):
            unit.online = event.online
            if not event.online and unit.cfg.role is Role.COMMAND:
                # a lost drive stops itself (command-zero timeout); on return it must not be
                # moved by a stale setpoint, nor switched on by a stale SERVO (it may have
                # lost its power: no automatic restart): zero, SERVO/START/brake forgotten,
                # and only a command heard after this may switch it on and move it again;
                # the drive that answers again is recognised anew before anything else
                unit.identified, unit.probe_since = None, event.t
                self.restrict(unit.name)  # its frame pushed: the probe again
            if unit.cfg.role is Role.COMMAND:
                self._readiness(unit.name)
        elif isinstance(event, GapEvent):
            self._gap(unit, event)
        elif isinstance(event, ForeignEvent):
            self._foreign(unit, event)
        elif isinstance(event, MalformedEvent):
            held = self._throttle.allow((unit.name, event.kind), event.t)
            if held is not None:
                self.notice(
                    unit.name,
                    logging.WARNING,
                    f"malformed {event.kind} ignored: {event.reason}{held_note(held)}",
                )

    def _foreign(self, unit: UnitState, event: ForeignEvent) -> None:
        """Another host on ``unit``'s drive (core/foreign.py), once per episode: a reader
        is reported; a commander stops the unit's robot with the safe word, sent at once,
        and keeps it stopped until the operator clears it (:meth:`clear_foreign`)."""
        host = event.host
        if not host.commanding:
            why = "reported (reads and unasked replies stop nothing)"
            self.notice(unit.name, logging.WARNING, f"{host.text()}: {why}")
            return
        robot = self.config.robot(unit.name)
        stopped = []
        for name in robot.units if robot is not None else (unit.name,):
            target = self.units[name]
            if target.cfg.role is not Role.COMMAND or self.stopping:
                continue
            self.gate.foreign.setdefault(name, f"{host.who()} (unit {unit.name})")
            self.restrict(name)  # consumed: nothing comes back when it is cleared
            self._send_at_once(target)
            stopped.append(name)
        self.notice(
            unit.name,
            logging.ERROR,
            f"{host.text()}: stopped {', '.join(stopped) or 'nothing (stopping)'} with the "
            f"safe word; clear it (clear_estop: TUI E, abh3 estop --clear) once that host has "
            f"been quiet for {QUIET_S:g} s",
        )

    def foreign_hosts(self, name: str) -> list[Foreign]:
        """Every other host heard on ``name``'s drive (core/foreign.py), commanding first."""
        unit = self.unit(name)
        return self.schedulers[unit.cfg.bus].foreign.of(name)

    def clear_foreign(self, source: str = "api") -> list[str]:
        """Lift the stops other hosts caused, where every such host on the unit's robot has
        been quiet for :data:`QUIET_S`; the arbitration is voided (nothing comes back by
        itself). The stops still standing, each with why."""
        now = self.clock()
        standing, cleared = [], []
        for name in list(self.gate.foreign):
            robot = self.config.robot(name)
            heard = [
                host
                for member in (robot.units if robot is not None else (name,))
                for host in self.schedulers[self.units[member].cfg.bus].foreign.commanding(
                    member, now
                )
            ]
            if heard:
                ago = now - max(h.last_commanding for h in heard)
                standing.append(
                    f"unit '{name}': {heard[0].who()} was heard {ago:.2f} s ago: not cleared "
                    f"until it has been quiet for {QUIET_S:g} s"
                )
                continue
            del self.gate.foreign[name]
            for member in robot.units if robot is not None else (name,):
                self.schedulers[self.units[member].cfg.bus].foreign.forgive(member)
            self.arbiter.hold(name)
            self._push(self.units[name])
            cleared.append(name)
        if cleared:
            self.notice(
                None,
                logging.WARNING,
                f"stop by another host cleared ({clean(source)}) on {', '.join(cleared)}; "
                "SERVO, START and motion must be given again",
            )
        for line in standing:
            self.notice(None, logging.WARNING, line)
        return standing

    def _gap(self, unit: UnitState, event: GapEvent) -> None:
        """No exchange for the outage bound (at most the drive's own timeout): it may have
        stopped itself, or lost its power and booted again; it must not restart on its
        own, so its switches are forgotten too."""
        bound = self.schedulers[unit.cfg.bus].slots[unit.name].outage
        if unit.cfg.role is Role.COMMAND:
            unit.gap = event.started
        if event.started:
            switched = bool(unit.inputs & moving_switches(unit.layout))
            self.restrict(unit.name)
            forgot = ", SERVO, START and brake release off: switch them on again"
            self.notice(
                unit.name,
                logging.WARNING,
                f"no exchange completed for {bound * 1000:.0f} ms: the drive may have stopped on "
                f"its command-zero timeout (drive_timeout_ms {unit.cfg.drive_timeout_ms}) or "
                f"lost its power; command zero{forgot if switched else ''}",
            )
        else:
            self.notice(unit.name, logging.INFO, "exchanges again after the gap; command zero")
        if unit.cfg.role is Role.COMMAND:
            self._readiness(unit.name)

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

    # ------------------------------------------------------------ the robot decision

    def _need(self, unit: UnitState) -> int:
        """SERVO and START of the unit's wheel axes (fixed by the file: made once)."""
        return self._needs[unit.name]

    def _switch(self, unit: UnitState, new: int) -> None:
        """Set the input word this supervisor commands; a change of its wheel axes'
        SERVO/START waits for the drive to report it anew (core/readiness.py)."""
        if (new ^ unit.inputs) & self._need(unit):
            unit.changed_at = self.clock()
            unit.reported = None
        unit.inputs = new

    def _view(self, unit: UnitState) -> DriveView:
        return DriveView(
            unit.name,
            unit.layout,
            unit.cfg.protocol,
            unit.wheels,
            unit.online,
            unit.gap,
            unit.identified,
            unit.inputs,
            unit.reported,
            unit.reported_error,
        )

    def enable(self, name: str, on: bool = True, source: str = "api") -> tuple[str, ...]:
        """SERVO and START on (``on``) or off every wheel axis of every drive of the robot
        ``name`` (or of the unit ``name``'s robot) as one act: refused whole, naming the
        drive and why, when one of them cannot take it now. The drives it switched; whether
        they followed, the robot decision says (:meth:`robot_unready`)."""
        robot = self.robot(name)
        units = [self._commandable(u) for u in robot.units]
        for unit in units:
            need = self._need(unit)
            self.gate.refuse_inputs(unit, unit.inputs | need if on else unit.inputs & ~need)
            if not on:
                continue
            # a drive that could not follow now (offline, in a gap, of the other generation)
            # refuses the whole robot: none of it is left switched on alone
            view = replace(
                self._view(unit), commanded=unit.inputs | need, reported=need, error=False
            )
            why = drive_unready(view)
            if why is not None and not why.pending:
                raise CommandError(f"robot '{robot.name}' not switched on: {unit.name}: {why.why}")
        for unit in units:
            need = self._need(unit)
            self.set_inputs(unit.name, need if on else 0, need)
        self.audit(source, None, f"{'enable' if on else 'disable'} robot {robot.name}")
        return robot.units

    def readiness(self) -> dict[str, str | None]:
        """Each robot (a unit of none: its own) and why it may not move now (None: ready,
        every drive of it reporting SERVO and START on; docs/safety.md)."""
        out: dict[str, str | None] = {}
        for name, (key, _) in self._group.items():
            if key not in out:
                why = self.robot_unready(name)
                out[key] = None if why is None else why.why
        return out

    def robot_unready(self, name: str) -> Unready | None:
        """Why the robot ``name`` (or the robot of the commanded unit ``name``) may not move
        now, or None."""
        if name not in self._group:
            name = self.robot(name).units[0]
        _, members = self._group[name]
        return robot_unready(self._view(self.units[u]) for u in members)

    def _readiness(self, name: str) -> None:
        """Decide ``name``'s robot again. Ready: every drive of it gets its setpoints. No
        longer ready: every drive of it gets zero in its next frame and what it was asked
        is consumed — only a command given after the recovery moves it."""
        key, members = self._group[name]
        why = self.robot_unready(name)
        ready = why is None
        if ready == self._ready[key]:
            return
        self._ready[key] = ready
        if ready:  # its setpoints go now, to every drive in the same instant
            for member in members:
                self._push(self.units[member])
                self._send_at_once(self.units[member])
            return
        assert why is not None
        moving = any(self.units[m].setpoint.ay or self.units[m].setpoint.bx for m in members)
        for member in members:
            self.arbiter.hold(member)
            self._zero(self.units[member])
        # said when it stopped motion or a drive let it down; not for a switch the operator
        # gave off, nor on the way out (its own lines say so)
        if not self.stopping and (moving or not (why.pending or "not switched on" in why.why)):
            self.notice(
                name,
                logging.WARNING,
                f"robot {key} stops: {why.why}; every drive of it gets zero and nothing moves "
                "until a command given after it is ready again",
            )

    def _identify(self, unit: UnitState, event: FeedbackEvent) -> bool:
        """What one reply shows of the drive's generation; True if that changed. A drive
        that answers in the other layout is held (core/gate.py) until it goes offline."""
        declared, known = unit.cfg.protocol, unit.identified
        if known is Generation.G2023 or (known is not None and known is not declared):
            # a 2023 control word may read as a consistent 2021 reply by chance: no evidence
            return False
        probed = known is None and event.sent_at is not None and event.sent_at >= unit.probe_since
        shown = reply_generation(event.data, probed)
        if shown is None or shown is known:
            return False
        unit.identified = shown
        if shown is not declared:
            self.restrict(unit.name)
            self.notice(
                unit.name,
                logging.ERROR,
                f"unit {unit.name} answers as a {shown} drive but the file says protocol: "
                f'"{declared}": held at a word safe in both generations (0x{flags.ID_PROBE:X}); '
                "correct the file's protocol and start again",
            )
        self._push(unit)
        return True

    def _ask_report(self, unit: UnitState, t: float) -> None:
        """A 2021 drive reports its switches in broadcast 1 only: asked for it while a
        change is not reported yet, and at least every 0.1 s while it is commanded on (a
        reboot or an error trip must be seen, whatever the polled packets)."""
        wanted = unit.inputs & self._need(unit)
        reported = unit.reported
        if wanted and (
            reported is None or wanted & ~reported or t - unit.reported_at >= REPORT_EVERY_S
        ):
            self.schedulers[unit.cfg.bus].request_status(unit.name, 1)

    def _report(self, unit: UnitState, control: int, error: bool, at: float, t: float) -> bool:
        """The drive's control word in an answer to a frame sent at ``at``, read in its
        identified layout; True if what the robot decision reads of it changed. A switch
        this supervisor commands on that the drive reports off — after it had reported it
        on, or after :data:`SETTLE_S` — is forgotten: no automatic restart."""
        if self.gate.stopping or unit.identified is not unit.cfg.protocol or at < unit.changed_at:
            return False  # on the way out the stop path reads the drives itself
        need = self._need(unit)
        wanted = unit.inputs & need
        had, had_error = unit.reported, unit.reported_error
        unit.reported, unit.reported_at, unit.reported_error = control, t, error
        missing = wanted & ~control
        if missing and ((had is not None and not wanted & ~had) or t >= unit.changed_at + SETTLE_S):
            self._dropped(unit, missing)
            return True
        return had is None or (had ^ control) & need != 0 or had_error != error

    def _dropped(self, unit: UnitState, missing: int) -> None:
        off = switch_names(unit.layout, missing)
        self.restrict(unit.name)
        self.notice(
            unit.name,
            logging.ERROR,
            f"drive of unit {unit.name} reports {off} off while this supervisor commands it "
            "on (it rebooted, lost power, tripped or did not follow): SERVO, START and brake "
            "release forgotten; switch them on again — nothing restarts by itself",
        )

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

    def robot(self, name: str) -> RobotConfig:
        """The robot called ``name``, or the robot of the unit called ``name``."""
        robot = self.config.robot(name)
        if robot is None:
            known = ", ".join(self.config.robots) or "none"
            raise CommandError(
                f"no robot named '{name}' and no commanded unit of one (robots: {known})"
            )
        return robot

    def zero(self, name: str) -> None:
        """Zero command in the unit's current mode (velocity or current); flags unchanged.
        Whoever drove the unit loses it: only a command given after this moves it."""
        unit = self._commandable(name)
        self.arbiter.hold(name)
        self._zero(unit)

    # Motion has an owner: every setpoint reaches a unit through the arbitration
    # (core/inputs.py), as an input source's command — a plugin's, a control client's, the
    # TUI's (plugin_host/feed.py), the start-up's (run_startup). The command language's
    # VEL/CUR given here (apply) is submitted as the source named, by default ``api:<unit>``.

    def _submit(self, name: str, command: Motion, source: str | None, *, standing: bool) -> None:
        """``command`` as ``source``'s (default ``api:<name>``, streamed) in the
        arbitration; refused (raised) if the unit cannot take it now, or if another source
        owns it."""
        state = self.unit(name)
        wanted = self._target(state, command)
        self._check(state, *wanted)
        owner = source if source is not None else f"{API_SOURCE}:{name}"
        if owner not in self.arbiter.sources:
            self.arbiter.add(_Own(owner, (name,), timeout=DEFAULT_TIMEOUT))
        if self.arbiter.closed:
            raise CommandError("the supervisor is stopping: commands are refused")
        self._checked = (command, {name: wanted})
        try:
            self.arbiter.submit(owner, command, self.clock(), standing=standing)
        finally:
            self._checked = None
        ay, bx, _ = wanted
        if self.units[name].setpoint.owner != owner and (ay or bx):
            holder = self.arbiter.owner(name)
            raise CommandError(
                f"unit '{name}' is driven by input {holder}: not applied"
                if holder is not None and holder != owner
                else f"unit '{name}' did not take the command (see the notices)"
            )

    def _target(self, unit: UnitState, command: InputCommand) -> tuple[float, float, ControlMode]:
        """The AY/BX values ``command`` asks of ``unit`` in its model, and their kind
        (a twist's: its robot's plan, made now)."""
        if isinstance(command, Stop):
            return 0.0, 0.0, unit.setpoint.kind
        if isinstance(command, CurrentCommand):
            return command.ay, command.bx, ControlMode.CURRENT
        if isinstance(command, VelocityCommand):
            return command.ay, command.bx, ControlMode.VELOCITY
        if isinstance(command, Twist):  # the robot's plan: one decision for all its drives
            motion = self._robot_of[unit.name]
            twist = command.linear_x, command.angular_z
            fields = motion.plan(*twist, self.clock()).fields
            ay, bx = fields[unit.name]
            return ay, bx, ControlMode.VELOCITY
        y, x = command.y, command.x
        if unit.cfg.velocity_model is VelocityModel.MOTOR:
            y, x = yx_to_ab(y, x)
        return y, x, ControlMode.VELOCITY

    def _arbitrated(self, name: str, command: InputCommand) -> bool:
        """The arbitration's winner for ``name`` (or zero): applied, owned by the source
        the arbitration names; False (and a notice) if the unit refused it."""
        unit = self.units[name]
        if isinstance(command, Stop):
            self._zero(unit)
            return True
        try:
            checked = self._checked
            if checked is not None and checked[0] is command and name in checked[1]:
                ay, bx, kind = checked[1][name]  # _submit checked it just now, on this stack
            else:
                self._commandable(name)
                _finite(*_values(command))
                ay, bx, kind = self._target(unit, command)
                self._check(unit, ay, bx, kind)
            self._set(unit, ay, bx, kind, self.arbiter.owner(name))
            if isinstance(command, Twist):
                self._twisted(name)
            else:
                self._robot_of[name].reset()
        except CommandError as exc:
            if unit.cfg.role is Role.COMMAND and not self.stopping:
                self._zero(unit)  # the owner asked for something else: not the old value
            held = self._throttle.allow((name, "refused"), self.clock())
            if held is not None:
                source = self.arbiter.owner(name) or "?"
                self.notice(
                    name, logging.WARNING, f"input {source} refused: {exc}{held_note(held)}"
                )
            return False
        return True

    def _twisted(self, name: str) -> None:
        """After a twist reached ``name``: the robot's clamp said (once a second per
        robot), and the ramp's next step set while it has not reached its target."""
        motion = self._robot_of[name]
        plan = motion.last
        if plan is None:
            return
        if plan.note is not None:
            held = self._throttle.allow((motion.robot.name, "clamped"), self.clock())
            if held is not None:
                self.notice(name, logging.WARNING, plan.note + held_note(held))
        if plan.ramping and not motion.step_pending and self.call_at is not None:
            motion.step_pending = True
            self.call_at(plan.t + motion.step_s, lambda: self._ramp_step(name))

    def _ramp_step(self, name: str) -> None:
        motion = self._robot_of[name]
        motion.step_pending = False
        current = self.arbiter.current.get(name)
        if current is not None and isinstance(current[1], Twist) and not self.stopping:
            self.arbiter.again(name)

    def set_inputs(self, name: str, data: int, mask: int) -> None:
        """Change the input bits selected by ``mask`` to those of ``data`` (seed inp_data)."""
        unit = self._commandable(name)
        layout = unit.layout
        if undefined := layout.undefined(data & mask):
            raise CommandError(
                f"bits 0x{undefined:08X} are not defined in the {layout.generation} input "
                f"word of unit '{name}': refused, nothing sent"
            )
        # an axis that drives no wheel is never switched on: SERVO ON ON takes the wheel's
        new = (unit.inputs & ~mask | data & mask) & 0xFFFFFFFF & ~idle_axes(unit)
        self.gate.refuse_inputs(unit, new)
        torque = new & layout.torque.both
        if torque != unit.inputs & layout.torque.both:
            # the meaning of the command fields changes: never reinterpret an old value
            kind = ControlMode.CURRENT if torque else ControlMode.VELOCITY
            self.arbiter.hold(name)
            unit.setpoint = Setpoint(kind=kind)
        self._switch(unit, new)
        self._push(unit)
        self._readiness(name)

    def _check(self, unit: UnitState, ay: float, bx: float, kind: ControlMode) -> None:
        """Refuse what the unit cannot take now: what the gate forbids, a robot that is
        not whole (a reason that resolves by itself is taken: held at zero until then),
        the wrong mode."""
        self.gate.refuse_motion(unit, ay, bx)
        if ay or bx:
            key, _ = self._group[unit.name]
            why = self.robot_unready(unit.name)
            if why is not None and not why.pending:
                raise CommandError(f"robot '{key}' may not move: {why.why}")
        both = unit.layout.torque.both
        torque = unit.inputs & both
        want = both if kind is ControlMode.CURRENT else 0
        if torque != want:
            mode = {0: "velocity", both: "current"}.get(torque, "mixed")
            raise CommandError(
                f"unit '{unit.name}' is in {mode} mode; a {kind} command needs "
                f"TORQUE {'ON ON' if want else 'OFF OFF'} first"
            )

    def refuse_motion(self, name: str, kind: ControlMode = ControlMode.VELOCITY) -> None:
        """Raise :class:`CommandError` if ``name`` may not move now, whatever the value:
        as a setpoint of ``kind`` is checked when applied (e-stop, held, a parameter write,
        stopping, a monitor, its robot not whole, the wrong mode) — so an entry that hands
        its command to the arbitration says the refusal in its own answer."""
        unit = self._commandable(name)
        self._check(unit, 1.0, 1.0, kind)

    def admit(self, name: str, command: VelocityCommand | CurrentCommand) -> str | None:
        """Check a ``VEL``/``CUR`` as it would be applied now, without applying it: raise
        :class:`CommandError` if refused; the clamp note if it would be clamped."""
        unit = self._commandable(name)
        _finite(command.ay, command.bx)
        kind = ControlMode.CURRENT if isinstance(command, CurrentCommand) else ControlMode.VELOCITY
        self._check(unit, command.ay, command.bx, kind)
        return _limited(unit, command.ay, command.bx, kind)[2]

    def _set(
        self, unit: UnitState, ay: float, bx: float, kind: ControlMode, owner: str | None
    ) -> None:
        """Store a setpoint the caller checked (:meth:`_check`), within the limits; an axis
        that drives no wheel (the motor model's, :attr:`UnitState.wheels`) keeps zero."""
        if len(unit.wheels) < 2:
            ay, bx = (ay if 0 in unit.wheels else 0.0), (bx if 1 in unit.wheels else 0.0)
        ay, bx, note = _limited(unit, ay, bx, kind)
        if note is not None:  # a stream beyond the limit (a joystick) says it once a second
            held = self._throttle.allow((unit.name, "clamped"), self.clock())
            if held is not None:
                self.notice(unit.name, logging.WARNING, note + held_note(held))
        self._store(unit, Setpoint(ay, bx, kind, owner if ay or bx else None))

    def _store(self, unit: UnitState, setpoint: Setpoint) -> None:
        unit.setpoint = setpoint
        self._push(unit)

    def _zero(self, unit: UnitState) -> None:
        """Zero command in the unit's current mode (velocity or current); its robot's next
        twist ramps from rest."""
        motion = self._robot_of.get(unit.name)
        if motion is not None:
            motion.reset()
        self._store(unit, Setpoint(kind=unit.setpoint.kind))

    def _push(self, unit: UnitState) -> None:
        """Hand the unit's frame, as the motion gate decides it, to its scheduler: the one
        way a command word reaches the wire."""
        if unit.cfg.role is not Role.COMMAND:
            return
        owner = unit.setpoint.owner
        owned = owner is not None and self.arbiter.owner(unit.name) == owner
        ready = self._ready[self._group[unit.name][0]]
        word = self.gate.word(unit, owned, ready)
        self.schedulers[unit.cfg.bus].set_payload(unit.name, word.payload())

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

    # ------------------------------------------------------------ command language

    def apply(
        self, name: str, command: Command, *, source: str | None = None, standing: bool = False
    ) -> None:
        """Apply a command-language record now. Motion (``VEL``/``CUR``) is ``source``'s
        in the arbitration (default ``api:<name>``, streamed; ``standing``: held while the
        source proves it is alive, as the start-up's is for the whole run)."""
        if isinstance(command, SwitchCommand | SelectCommand):
            change = commands.input_change(command, self.unit(name).layout)
            self.set_inputs(name, change.data, change.mask)
        elif isinstance(command, InputChange):
            self.set_inputs(name, command.data, command.mask)
        else:
            self._commandable(name)
            _finite(command.ay, command.bx)
            self._submit(name, command, source, standing=standing)

    def apply_text(
        self, name: str, text: str, *, source: str | None = None, standing: bool = False
    ) -> str:
        """Apply a command-language string now; answer as the seed's service does."""
        self.unit(name)  # an unknown unit is the caller's error, not the command's
        try:
            command = commands.parse_command(text)
        except CommandError:
            return commands.RESPONSE_INVALID
        try:
            self.apply(name, command, source=source, standing=standing)
        except CommandError as exc:
            return self.refusal(name, text, exc)
        return commands.RESPONSE_OK

    def run_startup(self, name: str) -> list[tuple[str, str]]:
        """The unit's ``startup:`` commands, now (:meth:`startup`); the answer to each, in
        order."""
        return [(text, self.startup(name, text).response) for text in self.unit(name).cfg.startup]

    def startup(self, name: str, text: str) -> CommandOutcome:
        """One line of the unit's ``startup:``, now, as the input source ``startup:<unit>``
        does it — an input like any other (core/inputs.py, :func:`enact`): its switches act
        at once, its motion is that source's standing command in the arbitration (present
        for the whole run: an owner the arbitration chose, until another source replaces
        it or the unit stops)."""
        source = f"{STARTUP_SOURCE}:{name}"

        def submit(command: Motion) -> None:
            if self.arbiter.closed:  # inputs stopped: nothing may command motion any more
                raise CommandError("the supervisor is stopping: commands are refused")
            if source not in self.arbiter.sources:
                self.arbiter.add(_Own(source, (name,), timeout=math.inf))
            self.arbiter.submit(source, command, self.clock(), standing=True)

        self.unit(name)  # an unknown unit is the caller's error, not the command's
        return enact(self, (name,), text, submit)

    def refusal(self, name: str, text: str, exc: CommandError) -> str:
        """The seed's answer to a command the unit refused, and a notice saying why."""
        if self.estop:
            return commands.packet_error(commands.PACKET_ESTOP)
        self.notice(name, logging.WARNING, f"{clean(text)!r} refused: {exc}")
        return commands.RESPONSE_INVALID

    async def command(self, name: str, text: str, *, source: str | None = None) -> str:
        """As :meth:`apply_text`, then wait for the drive to answer a frame carrying it."""
        since = self.clock()
        response = self.apply_text(name, text, source=source)
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

    @property
    def estop(self) -> bool:
        """The e-stop is latched (the motion gate's state)."""
        return self.gate.estop is not None

    @property
    def stopping(self) -> bool:
        """The way out has begun: every later command is refused (the gate's state)."""
        return self.gate.stopping

    def senders(self, bus: str, send: Callable[[str], None]) -> None:
        """Set by the runtime: send ``unit``'s frame on ``bus`` now, outside its schedule
        (the e-stop's frames go at once, not at each unit's next period)."""
        self._send_now[bus] = send

    def _commanded(self) -> list[UnitState]:
        return [u for u in self.units.values() if u.cfg.role is Role.COMMAND]

    def emergency_stop(self, source: str = "api") -> None:
        """Stop category 1 on every commanded unit, latched until cleared: zero and START
        off now (each unit's stop frame is sent at once), SERVO and brake release off once
        the drive reports it stopped (:mod:`.gate`). Whoever drove a unit loses it."""
        now = self.clock()
        first = self.gate.estop is None
        self.gate.latch(now)  # a second e-stop keeps the first one's time
        if first and self.call_at is not None:
            self.call_at(now + ESTOP_POWER_OFF_S, self._estop_deadline)
        for unit in self._commanded():
            self.arbiter.hold(unit.name)
            self._switch(unit, unit.inputs & ~unit.layout.start.both)
            self._zero(unit)
            self._send_at_once(unit)
        self.notice(
            None,
            logging.CRITICAL,
            f"EMERGENCY STOP ({clean(source)}): all units zero, START off; SERVO and brake "
            "release off once each drive reports it stopped (latched)",
        )
        if first:
            self._emit(EstopChange(now, True, clean(source)))

    def clear_emergency_stop(self, source: str = "api") -> list[str]:
        """Unlatch: nothing heard before this moment moves anything (the arbitration is
        voided again); START, SERVO and motion must be given anew. ``source``: who cleared
        it (the :class:`EstopChange` event says). The stops other hosts caused are cleared
        too where that host has gone quiet (:meth:`clear_foreign`): those still standing."""
        standing = self.clear_foreign(source) if self.gate.foreign else []
        if self.gate.estop is None:
            return standing
        for unit in self._commanded():  # not powered off yet: SERVO and brake go now too
            self._power_off(unit)
        self.gate.clear()
        for unit in self._commanded():
            self.arbiter.hold(unit.name)
            self._push(unit)
        self.notice(None, logging.WARNING, "emergency stop cleared; START must be given again")
        self._emit(EstopChange(self.clock(), False, clean(source)))
        return standing

    def _power_off(self, unit: UnitState) -> None:
        """The e-stop's second step: SERVO and brake release off (forgotten, not masked),
        the frame sent at once (an offline unit's next one may be a timeout away)."""
        if self.gate.power_off(unit.name):
            self._servo_off_now(unit)

    def _servo_off_now(self, unit: UnitState) -> None:
        """SERVO and brake release off (forgotten, not masked), the frame sent at once."""
        self._switch(unit, unit.inputs & ~moving_switches(unit.layout))
        self._push(unit)
        self._send_at_once(unit)

    @staticmethod
    def _standing(unit: UnitState, event: FeedbackEvent, since: float) -> bool:
        """The drive's answer to a frame sent at or after ``since`` says both axes stand."""
        feedback = unit.feedback
        return (
            event.sent_at is not None
            and event.sent_at >= since
            and feedback is not None
            and max(abs(feedback.vel_a), abs(feedback.vel_b)) < STOPPED_BELOW
        )

    def _send_at_once(self, unit: UnitState) -> None:
        """``unit``'s frame as just pushed, on the wire now, outside its schedule."""
        send = self._send_now.get(unit.cfg.bus)
        if send is not None:
            send(unit.name)

    def _estop_deadline(self) -> None:
        """ESTOP_POWER_OFF_S after the e-stop: every unit not powered off yet is, now."""
        estop = self.gate.estop
        if estop is not None and self.clock() >= estop.t + ESTOP_POWER_OFF_S - 1e-3:
            for unit in self._commanded():
                self._power_off(unit)

    def _estop_progress(self, unit: UnitState, event: FeedbackEvent) -> None:
        """A drive's answer to a frame sent after the e-stop that says it has stopped."""
        estop = self.gate.estop
        if estop is not None and self._standing(unit, event, estop.t):
            self._power_off(unit)

    def restrict(self, name: str) -> None:
        """``name`` entered a state that forbids motion (held, a parameter write): what it
        forbids is forgotten — SERVO, START, brake release, motion, the arbitration — so
        nothing comes back when the state ends; the frame is the gate's safe word."""
        unit = self.unit(name)
        if unit.cfg.role is not Role.COMMAND:
            return
        self.arbiter.hold(name)
        self._switch(unit, unit.inputs & ~moving_switches(unit.layout))
        self._zero(unit)

    @contextmanager
    def param_write(self, name: str) -> Iterator[None]:
        """The parameter-write lock of ``name`` for the ``with`` block: the unit sends the
        safe word and SERVO ON (from anyone) is refused until the block ends; refused at
        once while this supervisor commands its SERVO on."""
        unit = self.unit(name)
        if unit.cfg.role is not Role.COMMAND:
            yield
            return
        with self.gate.writing(unit):
            self.restrict(name)
            self._send_at_once(unit)  # the safe word before any write frame
            try:
                yield
            finally:
                self._push(unit)

    def begin_stop(self) -> None:
        """The normal way out, stop category 1: every command refused from now on; zero
        and START off on every commanded unit at once (its frame sent now), SERVO and
        brake release kept while its drive ramps down — off (the safe word, sent at once)
        as soon as the drive reports standing in an answer to a frame sent after this
        (:meth:`_stop_progress`), or at :meth:`hurry` / :meth:`safe_state`."""
        if self.gate.stopping:
            return
        self._stop_t = self.clock()
        self.gate.stopping = True
        self.arbiter.closed = True
        for unit in self._commanded():
            if unit.inputs & unit.layout.servo.both:
                self.gate.ramping.add(unit.name)
            self._switch(unit, unit.inputs & ~unit.layout.start.both)
            self._store(unit, Setpoint(kind=unit.setpoint.kind))
            self._send_at_once(unit)

    def hurry(self) -> None:
        """A second stop signal during the controlled stop: the safe word now, on every
        unit still ramping."""
        ramping, self.gate.ramping = self.gate.ramping, set()
        for name in ramping:
            self._servo_off_now(self.units[name])

    def _stop_progress(self, unit: UnitState, event: FeedbackEvent) -> None:
        """A drive's answer during the controlled stop: standing, it gets the safe word."""
        if unit.name in self.gate.ramping and self._standing(unit, event, self._stop_t):
            self.gate.ramping.discard(unit.name)
            self._servo_off_now(unit)

    def safe_state(self) -> None:
        """The way-out state on every unit we drove, final: zero velocity in the safe word
        (SERVO, START, brake release, torque and every other switch off; data select kept).
        """
        self.gate.ramping.clear()
        self.gate.stopping = True
        self.arbiter.closed = True  # nothing queued from a source may act any more
        for unit in self._commanded():
            self._switch(unit, unit.layout.safe(unit.inputs))
            self._store(unit, Setpoint())  # torque is off: the fields are velocities


class _Own(InputSource):
    """A source of the supervisor's own (``startup:<unit>``, ``api:<unit>``): it has no
    device and no thread; its commands are submitted by the Supervisor itself."""

    def start(self, feed: object) -> None:
        pass

    def stop(self) -> None:
        pass


def _values(command: InputCommand) -> tuple[float, ...]:
    if isinstance(command, Twist):
        return command.linear_x, command.angular_z
    if isinstance(command, VelocityYX):
        return command.y, command.x
    if isinstance(command, Stop):
        return ()
    return command.ay, command.bx


def _limited(
    unit: UnitState, ay: float, bx: float, kind: ControlMode
) -> tuple[float, float, str | None]:
    """The values within the unit's limit, its robot's axis limits and the wire's range,
    both axes scaled alike (the robot keeps its heading, only slower), and the note saying
    so if they changed."""
    velocity = kind is ControlMode.VELOCITY
    limit = unit.cfg.limits.velocity if velocity else unit.cfg.limits.current
    wire = VELOCITY if velocity else CURRENT
    scale = axes = 1.0  # the largest factors within the bounds (plain loops: no lists
    for v in (ay, bx):  # built for a setpoint that may come every exchange)
        if v:
            scale = min(scale, _bound(v, limit, wire) / abs(v))
    if velocity and unit.axis_limits is not None:
        motors = (ay, bx) if unit.cfg.velocity_model is VelocityModel.MOTOR else yx_to_ab(ay, bx)
        for v, m in zip(motors, unit.axis_limits, strict=True):
            if v:
                axes = min(axes, m / abs(v))
    if min(scale, axes) >= 1.0 - 1e-12:  # a robot's plan scaled exactly to the bound
        return ay, bx, None
    word, key = ("VEL", "velocity") if velocity else ("CUR", "current")
    # the binding bound: the robot's, the YAML's limit, or the wire's range
    if axes < scale:
        why = "the robot's limits: A ≤ {:.6g}, B ≤ {:.6g} min⁻¹".format(*unit.axis_limits or ())
    elif limit < wire.largest:
        why = f"limits.{key} {limit:g}"
    else:
        why = f"wire range {wire.minimum:g} … {wire.maximum:g}"
    scale = min(scale, axes)
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
