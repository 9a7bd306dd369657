"""Hardware health per unit and per bus, as ROS's ``diagnostic_msgs`` reports it.

Pure: it reads the supervisor's state and statistics at a given time and says OK, WARN,
ERROR or STALE (the levels of ``diagnostic_msgs/DiagnosticStatus``) with a message and
key/value pairs. The ROS 2 bridge publishes it on ``/diagnostics``; MCAP recordings keep
it. Rules, first that applies:

- ERROR: another host commands the unit's drive (or a drive of its robot), or it did and
  the stop it caused stands (core/foreign.py): key/values name the host and its frames;
- STALE: the unit never answered, or is offline (silent for its ``timeout_ms``);
- ERROR: error bits are set (by name);
- WARN: alarm bits are set, the drive's CAN settings differ from the file
  (core/verify.py), or a commanding unit achieves less than ``RATE_WARN`` of its
  requested command rate;
- OK otherwise.

Bits normal for the unit's role (a monitor's CAN_COMM_ERROR: its drive is never
commanded, :func:`abh3_supervisor.core.readouts.normal_faults`) count as neither error nor
alarm: they are a note in the message ("online, no commands (monitor)").

:class:`Health` reads the live supervisor (the loop's recordings use it on the loop);
:class:`HealthSnapshot` is what a plugin gets (``SupervisorView.health()``): the statuses
at one time, frozen, plain values only — nothing of the supervisor reachable from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from abh3_supervisor.config.model import Role
from abh3_supervisor.core import readouts
from abh3_supervisor.core.foreign import QUIET_S
from abh3_supervisor.core.planner import plan
from abh3_supervisor.core.state import UnitState
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.bus_health import BusHealth, BusState
from abh3_supervisor.scheduler.core import BusScheduler

RATE_WARN = 0.8  # achieved/requested below this is worth a look (a slow drive, a busy bus)
RATE_WINDOW_S = 2.0  # the achieved rate is measured over this window
RATE_SAMPLES = 10  # replies before the rate means anything (not at start-up)
PREFIX = "abh3_supervisor"  # names read "abh3_supervisor: unit left" in rqt_robot_monitor


class Level(IntEnum):
    """``diagnostic_msgs/DiagnosticStatus`` levels (byte constants of the message)."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


@dataclass(frozen=True, slots=True)
class Status:
    level: Level
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...]


def _word(unit: UnitState, name: str) -> tuple[int | None, readouts.Faults]:
    value = unit.words.get(name)
    return value, readouts.read_faults(unit.cfg.role, value)


def _hex(value: int | None) -> str:
    return "" if value is None else f"0x{value:08X}"


def unit_status(
    unit: UnitState, scheduler: BusScheduler, now: float, stopped: str | None = None
) -> Status:
    """``stopped``: why the unit stands stopped for another host (the gate's reason)."""
    cfg = unit.cfg
    stats = scheduler.slots[cfg.name].stats
    error, error_bits = _word(unit, "error")
    alarm, alarm_bits = _word(unit, "alarm")
    errors, alarms = error_bits.names, alarm_bits.names
    notes = "; ".join(dict.fromkeys(error_bits.notes + alarm_bits.notes))
    achieved = stats.achieved_rate_hz(now, RATE_WINDOW_S)
    requested = cfg.command_rate_hz
    commanding = cfg.role is Role.COMMAND
    supplies = unit.status.get(5)
    verification = unit.verify
    mismatches = "; ".join(r.line() for r in verification.mismatches)
    brd5 = supplies[1] if supplies is not None else None
    heard = [h for h in scheduler.foreign.of(cfg.name) if now - h.last <= QUIET_S]
    commanders = [h for h in heard if h.commanding]
    if stopped is not None or commanders:
        why = stopped or commanders[0].who()
        level, message = Level.ERROR, f"stopped: {why}"
    elif unit.online is None:
        level, message = Level.STALE, "no answer yet"
    elif unit.online is False:
        level, message = Level.STALE, f"offline: silent for {cfg.timeout_ms} ms or more"
    elif unit.identified not in (None, cfg.protocol):  # identity before energy: held
        level, message = (
            Level.ERROR,
            f"answers as a {unit.identified} drive, the file says protocol: {cfg.protocol}: "
            "held at a word safe in both generations",
        )
    elif errors:  # every set bit has a name (``bitN`` where the manual gives none)
        level, message = Level.ERROR, "error: " + ", ".join(errors)
    elif alarms:
        level, message = Level.WARN, "alarm: " + ", ".join(alarms)
    elif mismatches:
        level, message = Level.WARN, f"drive settings differ from the file: {mismatches}"
    elif held := verification.holds():  # verify: refuse fails closed: say why it is held
        level, message = Level.WARN, f"held at its idle word: {held}"
    elif commanding and achieved < RATE_WARN * requested and stats.replies >= RATE_SAMPLES:
        level, message = Level.WARN, f"command rate {achieved:.1f} of {requested:g} Hz"
    else:
        level, message = Level.OK, "online"
    if notes and unit.online:
        message += f"; {notes}" if level is not Level.OK else f", {notes}"
    differ = f"drive settings differ from the file: {mismatches}"
    if mismatches and not message.startswith(differ):  # under a worse state: still said
        message += f"; {differ}"
    rtt = stats.rtt_ms(99)
    values = [
        ("online", {None: "unknown", True: "yes", False: "no"}[unit.online]),
        ("bus", cfg.bus),
        ("abh3_id", str(cfg.abh3_id)),
        ("protocol", cfg.protocol.value),
        ("generation its replies show", "" if unit.identified is None else str(unit.identified)),
        ("role", cfg.role.value),
        ("error", _hex(error)),
        ("error bits", ", ".join(error_bits.labelled())),
        ("alarm", _hex(alarm)),
        ("alarm bits", ", ".join(alarm_bits.labelled())),
        ("command rate achieved [Hz]", f"{achieved:.1f}"),
        ("command rate requested [Hz]", f"{requested:g}"),
        ("replies", str(stats.replies)),
        ("timeouts", str(stats.timeouts)),
        ("send errors", str(stats.send_errors)),
        ("malformed frames", str(stats.malformed)),
        ("gaps", str(stats.gaps)),
        ("round trip p99 [ms]", "" if rtt is None else f"{rtt:.2f}"),
        ("drive settings", verification.state.value),
        ("drive settings differ", mismatches),
    ]
    for host in heard:  # every other host heard lately, commanding first
        values += [("foreign host", f"0x{host.source:02X}"), ("foreign frames", host.text())]
    if isinstance(brd5, frames.Brd5):
        values += [
            ("main supply [V]", f"{brd5.main_volt:.1f}"),
            ("control supply [V]", f"{brd5.control_volt:.1f}"),
        ]
    return Status(
        level,
        f"{PREFIX}: unit {cfg.name}",
        message,
        f"abh3 {cfg.bus}/{cfg.abh3_id}",
        tuple(values),
    )


def robot_status(sup: Supervisor, name: str, why: str | None) -> Status:
    """A robot as the robot decision sees it (docs/safety.md): OK while every drive of it
    reports SERVO and START on; WARN naming the drive and why it may not move."""
    robot = sup.config.robot(name)
    units = robot.units if robot is not None else (name,)
    level, message = (Level.OK, "ready") if why is None else (Level.WARN, f"not ready: {why}")
    return Status(
        level,
        f"{PREFIX}: robot {name}",
        message,
        f"abh3 robot {name}",
        (("drives", ", ".join(units)), ("ready", "yes" if why is None else "no")),
    )


@dataclass(frozen=True, slots=True)
class BusLoad:
    """Frames per second measured between two reports, and the load they make."""

    frames_per_s: float
    load_percent: float


def frames_seen(units: list[UnitState], scheduler: BusScheduler) -> int:
    """Frames the scheduler sent and answers it counted, all units of a bus."""
    slots = [scheduler.slots[u.name].stats for u in units]
    return sum(s.commands_sent + s.replies + s.polls_sent + s.broadcasts for s in slots)


def bus_status(
    name: str,
    units: list[UnitState],
    scheduler: BusScheduler,
    planned_load: float,
    measured: BusLoad | None = None,
    health: BusHealth | None = None,
) -> Status:
    """A bus: ERROR when its interface is bus-off or no unit on it answers (cable, power,
    bitrate), WARN when the interface reports trouble (error-passive, a full queue), some
    units do not answer or sends fail; with the frame counts and the load."""
    slots = [scheduler.slots[u.name].stats for u in units]
    online = sum(u.online is True for u in units)
    send_errors = sum(s.send_errors for s in slots)
    state, detail = (health.state, health.detail) if health else (BusState.OK, "")
    if state is BusState.BUS_OFF:
        level, message = Level.ERROR, f"{state}: {detail}"
    elif units and online == 0:
        level, message = Level.ERROR, "no unit answers"
    elif state is not BusState.OK:
        level, message = Level.WARN, f"{state}: {detail}"
    elif online < len(units):
        level, message = Level.WARN, f"{online} of {len(units)} units answer"
    elif send_errors:
        level, message = Level.WARN, f"{send_errors} frames could not be sent"
    else:
        level, message = Level.OK, f"{len(units)} units answer"
    values = (
        ("interface", str(state)),
        ("units online", f"{online}/{len(units)}"),
        ("load [%]", "" if measured is None else f"{measured.load_percent:.1f}"),
        ("frames/s", "" if measured is None else f"{measured.frames_per_s:.0f}"),
        ("planned load [%]", f"{planned_load:.1f}"),
        ("frames", str(frames_seen(units, scheduler))),
        ("send errors", str(send_errors)),
        ("timeouts", str(sum(s.timeouts for s in slots))),
        ("malformed frames", str(sum(s.malformed for s in slots))),
    )
    return Status(level, f"{PREFIX}: bus {name}", message, f"can {name}", values)


LOAD_SPAN_S = 0.5  # shortest span a measured load is taken over


@dataclass(frozen=True, slots=True)
class HealthSnapshot:
    """Every bus's, unit's and robot's status at ``t`` (the supervisor's clock), as
    ``/diagnostics`` reports them: frozen records of strings and numbers, a copy — keep it,
    read it from any thread; it never changes (ask the view for a new one)."""

    t: float
    report: tuple[Status, ...]

    def statuses(self, now: float | None = None) -> list[Status]:
        """The statuses, as of :attr:`t` (a new list each call). ``now`` is ignored: it is
        taken so that code written for :meth:`Health.statuses` reads a snapshot too."""
        return list(self.report)


class Health:
    """The statuses of a supervisor's buses and units: every bus, then its units, in the
    file's order. Each bus's load is measured between reports at least LOAD_SPAN_S apart,
    in bits as the planner counts them for this bus's mix of frames. It reads the live
    supervisor: a plugin gets :class:`HealthSnapshot` instead (its view's ``health()``)."""

    def __init__(self, sup: Supervisor) -> None:
        self.sup = sup
        self.plans = {p.bus: p for p in plan(sup.config)}
        self._mark: dict[str, tuple[float, int]] = {}  # bus → (time, frames) measured from
        self._load: dict[str, BusLoad] = {}

    def statuses(self, now: float) -> list[Status]:
        out: list[Status] = []
        for bus, scheduler in self.sup.schedulers.items():
            units = [u for u in self.sup.units.values() if u.cfg.bus == bus]
            p = self.plans[bus]
            self._measure(bus, frames_seen(units, scheduler), now)
            health = self.sup.bus_health[bus]
            load = self._load.get(bus)
            out.append(bus_status(bus, units, scheduler, p.load_percent, load, health))
            stops = self.sup.gate.foreign
            out += [unit_status(u, scheduler, now, stops.get(u.name)) for u in units]
        out += [robot_status(self.sup, name, why) for name, why in self.sup.readiness().items()]
        return out

    def snapshot(self, now: float) -> HealthSnapshot:
        """:meth:`statuses` at ``now``, frozen: nothing live in it."""
        return HealthSnapshot(now, tuple(self.statuses(now)))

    def _measure(self, bus: str, frames: int, now: float) -> None:
        since, before = self._mark.setdefault(bus, (now, frames))
        if now - since < LOAD_SPAN_S:
            return
        p = self.plans[bus]
        per_s = (frames - before) / (now - since)
        bits = p.bits_per_s / p.frames_per_s if p.frames_per_s else 0.0
        self._load[bus] = BusLoad(per_s, 100 * per_s * bits / p.bitrate)
        self._mark[bus] = (now, frames)
