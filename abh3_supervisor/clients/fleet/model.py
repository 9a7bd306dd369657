"""What the broker has said about the fleet, fed message by message: no network, no
Textual, no clock of its own (every call gives the time), so every state is testable.

It never claims what it has not seen: a robot is online only while its retained
``status`` says so; a unit's values are live only when a message arrived live (not a
retained copy) within ``stale_s`` and its robot is online — anything else is shown as of
its age, greyed. A payload that is malformed or of another version is counted and
described, never obeyed and never a crash.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

from abh3_supervisor.clients.fleet import reading
from abh3_supervisor.clients.fleet.reading import Malformed, WrongVersion
from abh3_supervisor.fleet import PREFIX, Where, where
from abh3_supervisor.fleet.payloads import STATES

EVENTS_KEPT = 30  # per robot: the recent ones the view lists
STALE_S = 2.0  # 4 periods of the default 2 Hz unit state
HEALTH_STALE_S = 15.0  # 3 periods of the 5 s health


@dataclass
class Unit:
    name: str
    online: bool | None = None
    servo: tuple[bool | None, bool | None] = (None, None)
    start: tuple[bool | None, bool | None] = (None, None)
    commanded: tuple[float | None, ...] = (None, None)  # ay, bx
    measured: tuple[float | None, ...] = (None, None)  # a, b
    errors: tuple[str, ...] = ()
    alarms: tuple[str, ...] = ()
    owner: str | None = None
    estop: bool = False
    verify: str = ""
    foreign_host: dict[str, Any] | None = None
    report_age_s: float | None = None  # the drive's report's age when it was published
    sent: float = 0.0  # the payload's time (the robot's clock)
    received: float = 0.0  # our clock
    retained: bool = True  # only a retained copy seen so far (the broker's, maybe old)

    def seen(self) -> float:
        """When these values were true: our receive time of a live message, the robot's
        own time of a retained copy (the broker may have held it for hours)."""
        return self.sent if self.retained else self.received


@dataclass
class Event:
    time: float  # the robot's clock
    received: float
    unit: str | None
    kind: str
    text: str
    data: dict[str, Any]


@dataclass
class Robot:
    fleet_id: str
    state: str | None = None  # its retained status; None: none seen
    status_time: float = 0.0
    name: str = ""  # the robot's name in its YAML
    host: str = ""
    pid: int | None = None
    version: str = ""
    declared: tuple[str, ...] = ()  # the units its status lists
    attach: str | None = None
    units: dict[str, Unit] = field(default_factory=dict)
    events: deque[Event] = field(default_factory=lambda: deque(maxlen=EVENTS_KEPT))
    health: dict[str, Any] | None = None
    health_received: float = 0.0
    last_seen: float | None = None  # our clock, any live message
    malformed: int = 0
    wrong_version: int = 0
    problem: str = ""  # the last malformed payload, said

    @property
    def online(self) -> bool:
        return self.state == "online"


class FleetModel:
    """Every robot and unit under ``prefix`` the broker has told us about."""

    def __init__(self, prefix: str = PREFIX, stale_s: float = STALE_S) -> None:
        self.prefix, self.stale_s = prefix, stale_s
        self.robots: dict[str, Robot] = {}
        self.malformed = 0  # all robots', and those of topics naming none
        self.wrong_version = 0
        self.unknown_topics = 0
        self.messages = 0
        self.problem = ""

    def feed(self, topic: str, payload: bytes, retained: bool, now: float) -> None:
        """One message as received at ``now`` (seconds since the epoch, our clock)."""
        self.messages += 1
        place = where(topic, self.prefix)
        if place is None or place.kind in ("unknown", "command"):
            # commands (ours and others') are not state; other topics are not ours
            self.unknown_topics += place is not None and place.kind == "unknown"
            return
        robot = self.robots.get(place.fleet_id) or Robot(place.fleet_id)
        try:
            obj = reading.decode(payload)
            self._apply(robot, place, obj, retained, now)
        except Malformed as exc:
            self._count(robot, place, exc)
            return
        self.robots[robot.fleet_id] = robot
        if not retained:
            robot.last_seen = max(now, robot.last_seen or now)

    def _count(self, robot: Robot, place: Where, exc: Malformed) -> None:
        wrong = isinstance(exc, WrongVersion)
        what = f"{place.kind}{'' if place.unit is None else ' of ' + place.unit}: {exc}"
        robot.problem = self.problem = f"{robot.fleet_id} {what}"
        if wrong:
            robot.wrong_version += 1
            self.wrong_version += 1
        else:
            robot.malformed += 1
            self.malformed += 1
        self.robots[robot.fleet_id] = robot  # shown, with its count, even if nothing else

    def _apply(
        self, robot: Robot, place: Where, obj: dict[str, Any], retained: bool, now: float
    ) -> None:
        if obj.get("fleet_id") != robot.fleet_id:
            raise Malformed(f"fleet_id {obj.get('fleet_id')!r} is not its topic's")
        if place.kind == "status":
            self._status(robot, obj)
        elif place.kind == "state":
            self._unit(robot, str(place.unit), obj, retained, now)
        elif place.kind == "events":
            robot.events.append(_event(obj, now))
        elif place.kind == "health":
            if not isinstance(obj.get("buses"), dict) or not isinstance(obj.get("mqtt"), dict):
                raise Malformed("health without buses and mqtt objects")
            robot.health, robot.health_received = obj, now

    def _status(self, robot: Robot, obj: dict[str, Any]) -> None:
        """The broker's status, taken as it comes, retained or not: its retained one is
        the current one by definition. (Not by time: a last will is built when its robot
        connects, so it is older than the birth it follows.)"""
        state = reading.text(obj, "state")
        if state not in STATES:
            raise Malformed(f"state {state!r} is not one of {', '.join(STATES)}")
        sent = reading.number(obj, "time") or 0.0
        attach = reading.text(obj, "attach", none=True)
        units = reading.names(obj, "units")
        pid = obj.get("pid")
        robot.state, robot.status_time, robot.declared, robot.attach = state, sent, units, attach
        robot.name = str(obj.get("robot", ""))
        robot.host, robot.version = str(obj.get("host", "")), str(obj.get("version", ""))
        robot.pid = pid if isinstance(pid, int) and not isinstance(pid, bool) else None

    def _unit(
        self, robot: Robot, name: str, obj: dict[str, Any], retained: bool, now: float
    ) -> None:
        if obj.get("unit") != name:
            raise Malformed(f"unit {obj.get('unit')!r} is not its topic's")
        sent = reading.number(obj, "time") or 0.0
        old = robot.units.get(name)
        if retained and old is not None and sent <= old.sent:
            return  # an older (or the same) copy replayed by the broker
        foreign = obj.get("foreign_host")
        if foreign is not None and not isinstance(foreign, dict):
            raise Malformed(f"foreign_host {foreign!r} is not an object or null")
        estop = obj.get("estop")
        if not isinstance(estop, bool):
            raise Malformed(f"estop {estop!r} is not true or false")
        unit = Unit(
            name,
            online=reading.flag(obj.get("online"), "online"),
            servo=reading.pair(obj, "servo"),
            start=reading.pair(obj, "start"),
            commanded=reading.axes(obj, "commanded", ("ay", "bx")),
            measured=reading.axes(obj, "measured", ("a", "b")),
            errors=reading.names(obj, "errors"),
            alarms=reading.names(obj, "alarms"),
            owner=reading.text(obj, "owner", none=True),
            estop=estop,
            verify=reading.text(obj, "verify") or "",
            foreign_host=foreign,
            report_age_s=reading.number(obj, "age_s", none=True),
            sent=sent,
            received=now,
            retained=retained,
        )
        robot.units[name] = unit

    # -- what the view asks ------------------------------------------------------------

    def sorted_robots(self) -> list[Robot]:
        return [self.robots[k] for k in sorted(self.robots)]

    def unit_names(self, robot: Robot) -> list[str]:
        """Its units: those it declares (seen or not) and any it published."""
        return sorted(set(robot.declared) | set(robot.units))

    def live(self, robot: Robot, unit: Unit, now: float) -> bool:
        """Values seen live, recently, from a robot whose status says online."""
        return robot.online and not unit.retained and now - unit.received <= self.stale_s

    def age(self, unit: Unit, now: float) -> float:
        return max(0.0, now - unit.seen())

    def health_live(self, robot: Robot, now: float) -> bool:
        return robot.health is not None and now - robot.health_received <= HEALTH_STALE_S


def _event(obj: dict[str, Any], now: float) -> Event:
    data = obj.get("data")
    if not isinstance(data, dict):
        raise Malformed(f"data {data!r} is not an object")
    return Event(
        time=reading.number(obj, "time") or 0.0,
        received=now,
        unit=reading.text(obj, "unit", none=True),
        kind=reading.text(obj, "kind") or "",
        text=reading.text(obj, "text") or "",
        data=data,
    )
