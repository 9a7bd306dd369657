"""The ``mqtt`` plugin's hooks: what the supervisor says goes to each robot's link, what
the fleet asks is judged here (docs/fleet.md).

Every hook builds a payload from the read-only view and queues it (outbox.py): none
waits for the network. Unit states also go out at ``state_rate_hz`` from a timer thread
of ours, and at once when a unit's safety state changes. Commands arrive on paho's
thread and are judged there: allowed, not retained, fresh, well-formed, ``seq`` rising —
then the e-stop goes through the view's ``emergency_stop`` (the one gate every e-stop
goes through), its clearing through ``clear_emergency_stop``, a twist through this
plugin's input source, under the owner rule of every input.
"""

from __future__ import annotations

import functools
import importlib.util
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from abh3_plugins.mqtt.settings import Settings, parse, schema
from abh3_supervisor.plugin_api import (
    THREADS_BELOW_LOOP,
    CommandError,
    Config,
    EstopChange,
    FlagChange,
    InputFeed,
    InputSource,
    Notice,
    OwnerChange,
    RobotConfig,
    Section,
    SupervisorView,
    UnitView,
    fleet,
    hookimpl,
    motor_speeds,
)

payloads = fleet.payloads

if TYPE_CHECKING:  # paho is the mqtt extra's: imported when a run starts, not to check
    import paho.mqtt.client as mqtt

    from abh3_plugins.mqtt.link import Link

log = logging.getLogger("abh3_plugins.mqtt")
ABH3_API_VERSION = "1.2"  # the plugin API this is written for (abh3_threads)
WARN_EVERY_S = 5.0  # a refusal's log line, per robot and topic
REFUSAL_EVENTS_PER_S = 10  # beyond, per robot, refusals are counted into the next event
NEEDS = {"estop": "allow_estop", "estop_clear": "allow_estop_clear", "twist": "allow_commands"}


class FleetSource(InputSource):
    """A robot's motion from the fleet (``mqtt:{fleet_id}``): its units are the robot's,
    silence longer than ``command_timeout_ms`` is zero."""

    def __init__(self, robot: RobotConfig, fid: str, settings: Settings) -> None:
        super().__init__(f"mqtt:{fid}", robot.units, settings.priority, settings.command_timeout_s)
        self.robot = robot
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None  # from now on every twist is dropped


def report(view: SupervisorView, unit: UnitView) -> fleet.UnitReport:
    """A unit's state in the contract's words, from the live view (any thread)."""
    words = unit.words
    control = words.get("control")
    layout = unit.layout

    def pair(mask_ay: int, mask_bx: int) -> tuple[bool | None, bool | None]:
        if control is None:
            return None, None
        return bool(control & mask_ay), bool(control & mask_bx)

    fb = unit.feedback
    setpoint = unit.setpoint
    error, alarm = words.get("error"), words.get("alarm")
    # another host on the drive while it is heard (as /diagnostics says it), commanding first
    lately = [h for h in view.foreign_hosts(unit.name) if h.lately]
    return fleet.UnitReport(
        unit=unit.name,
        online=unit.online,
        servo=pair(layout.servo.ay, layout.servo.bx),
        start=pair(layout.start.ay, layout.start.bx),
        commanded=(setpoint.ay, setpoint.bx),
        measured=(None, None) if fb is None else (fb.vel_a, fb.vel_b),
        errors=() if error is None else tuple(unit.names("error", error)),
        alarms=() if alarm is None else tuple(unit.names("alarm", alarm)),
        owner=view.owner(unit.name),
        estop=view.estop,
        verify=str(unit.verify.state),
        foreign_host=(lately[0].source, lately[0].frames) if lately else None,
        age_s=None if fb is None else max(0.0, view.now() - fb.t),
    )


class Throttle:
    """True once per ``every`` seconds per key."""

    def __init__(self, every: float) -> None:
        self.every = every
        self._last: dict[Any, float] = {}

    def __call__(self, key: Any) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -math.inf) < self.every:
            return False
        self._last[key] = now
        return True


class MqttPlugin:
    def __init__(self) -> None:
        self.settings = Settings(name="-")
        self.view: SupervisorView | None = None
        self.links: dict[str, Link] = {}  # by robot
        self.robot_of: dict[str, str] = {}  # unit → the robot whose link carries it
        self.sources: dict[str, FleetSource] = {}  # by robot
        self.seqs = fleet.SeqGuard(0.5)
        self._published: dict[str, tuple[Any, ...]] = {}  # unit → its safety state sent
        self._lock = threading.Lock()
        self._warn = Throttle(WARN_EVERY_S)
        self._refusals: dict[str, tuple[float, int, int]] = {}  # robot → (second, sent, more)
        self._stop = threading.Event()
        self._timer: threading.Thread | None = None

    # ------------------------------------------------------------ configuration

    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        return schema()

    @hookimpl
    def abh3_configure(self, section: Section, config: Config) -> None:
        self.settings = parse(section, config)
        self.seqs = fleet.SeqGuard(self.settings.command_timeout_s)
        if importlib.util.find_spec("paho") is None:
            section.error(
                "broker",
                "the mqtt plugin needs paho-mqtt: pip install 'abh3-supervisor[mqtt]' (in a "
                "clone: pip install -e '.[mqtt]'; or pip install paho-mqtt)",
            )

    # ------------------------------------------------------------ start

    @hookimpl
    def abh3_threads(self) -> str:
        # short work between sleeps (paho's network thread, the sender, the state timer):
        # at normal priority, preempted while holding the GIL under a flood, they held the
        # bus loop up by 3–5 ms (docs/performance.md, "DP0 timing against the broker")
        return THREADS_BELOW_LOOP

    @hookimpl
    def abh3_start(self, supervisor: SupervisorView) -> None:
        from abh3_plugins.mqtt.link import Link  # paho: only now

        self.view = s = supervisor
        settings = self.settings
        for robot in s.config.robots.values():
            units = [u for u in robot.units if u in s.units]
            if not units:
                continue
            fid = fleet.fleet_id(settings.name, robot.name)
            self.links[robot.name] = Link(
                settings,
                fid,
                robot.name,
                units,
                on_message=self._message,
                on_lost=self._lost,
            )
            for unit in units:
                self.robot_of.setdefault(unit, robot.name)
        for link in self.links.values():
            link.start()  # connects in paho's thread: the broker may be down, we go on
        self._timer = threading.Thread(target=self._periodic, name="mqtt states", daemon=True)
        self._timer.start()
        allowed = [k for k, v in NEEDS.items() if getattr(settings, v)]
        log.log(
            logging.WARNING if allowed else logging.INFO,
            "mqtt: %d robot(s) on %s (%s) as %s; fleet commands %s",
            len(self.links),
            settings.url,
            f"MQTT {settings.protocol}",
            ", ".join(link.fleet_id for link in self.links.values()),
            f"ALLOWED: {', '.join(allowed)}" if allowed else "off",
        )

    @hookimpl
    def abh3_input_sources(self, register: Callable[[InputSource], None]) -> None:
        if not self.settings.allow_commands or self.view is None:
            return
        for name, link in self.links.items():
            source = self.sources[name] = FleetSource(
                self.view.robot(name), link.fleet_id, self.settings
            )
            register(source)

    # ------------------------------------------------------------ what goes out

    def publish_state(self, unit: str, *, changed_only: bool = False) -> None:
        """``unit``'s state, now; ``changed_only``: only when its safety state changed."""
        view, name = self.view, self.robot_of.get(unit)
        if view is None or name is None:
            return
        link = self.links[name]
        r = report(view, view.units[unit])
        qos = self.settings.qos["state"]
        with self._lock:  # queued under it too: the state remembered is the last one queued
            before = self._published.get(unit)
            if changed_only and before == r.safety():
                return
            self._published[unit] = r.safety()
            link.put(
                link.topics.state(unit),
                functools.partial(
                    payloads.unit_state, fleet_id=link.fleet_id, robot=name, report=r
                ),
                qos,
                retain=True,
                lossy=True,
            )
        if before is not None and before[-2] != r.verify != "pending":  # an outcome
            self.event(link, unit, "verify", f"unit {unit}: verify {before[-2]} → {r.verify}")
        if before is not None and before[-1] != r.safety()[-1]:
            self.event(link, unit, "foreign_host", *_foreign_news(unit, r.foreign_host))

    def event(
        self, link: Link, unit: str | None, kind: str, text: str, data: dict[str, Any] | None = None
    ) -> None:
        link.put(
            link.topics.events,
            functools.partial(
                payloads.event,
                fleet_id=link.fleet_id,
                robot=link.robot,
                unit=unit,
                kind=kind,
                text=text,
                data=data,
            ),
            self.settings.qos["events"],
            retain=False,
            lossy=False,
        )

    def publish_health(self) -> None:
        view = self.view
        if view is None:
            return
        buses = {
            name: {
                "frames_sent": c.frames_sent,
                "frames_received": c.frames_received,
                "send_errors": c.send_errors,
                "state": c.state,
            }
            for name, c in view.bus_counters().items()
        }
        for link in self.links.values():
            ours = {b: buses[b] for b in sorted({view.units[u].cfg.bus for u in link.units})}
            link.put(
                link.topics.health,
                functools.partial(
                    payloads.health,
                    fleet_id=link.fleet_id,
                    robot=link.robot,
                    buses=ours,
                    queued=len(link.outbox),
                    dropped=link.outbox.dropped,
                    reconnects=link.reconnects,
                    not_heard=list(link.not_heard),
                ),
                self.settings.qos["health"],
                retain=True,
                lossy=True,
            )

    def _periodic(self) -> None:
        period = 1.0 / self.settings.state_rate_hz
        next_state = next_health = time.monotonic()
        while not self._stop.wait(max(0.0, min(next_state, next_health) - time.monotonic())):
            now = time.monotonic()
            if now >= next_state:
                for unit in self.robot_of:
                    self.publish_state(unit)
                next_state = max(next_state + period, now)
            self._say_unsaid()
            if now >= next_health:
                self.publish_health()
                next_health = max(next_health + self.settings.health_s, now)

    def _link_of(self, unit: str | None) -> list[Link]:
        name = self.robot_of.get(unit) if unit is not None else None
        return [self.links[name]] if name is not None else list(self.links.values())

    @hookimpl
    def abh3_health(self, unit: str, online: bool) -> None:
        self.publish_state(unit, changed_only=True)
        for link in self._link_of(unit):
            kind = "unit_online" if online else "unit_offline"
            text = f"unit {unit}: {'online' if online else 'offline (silent for its timeout)'}"
            self.event(link, unit, kind, text)

    @hookimpl
    def abh3_flags(self, change: FlagChange) -> None:
        set_, cleared = self.view.flag_names(change) if self.view is not None else ([], [])
        if change.word in ("error", "alarm") and (set_ or cleared):  # not a first "none"
            text = f"unit {change.unit}: {change.word}"
            text += "".join(
                f"; {what} {', '.join(names)}"
                for what, names in (("set", set_), ("cleared", cleared))
                if names
            )
            for link in self._link_of(change.unit):
                data = {"word": change.word, "set": set_, "cleared": cleared, "value": change.new}
                self.event(link, change.unit, change.word, text, data)
        self.publish_state(change.unit, changed_only=True)

    @hookimpl
    def abh3_estop(self, event: EstopChange) -> None:
        kind = "estop_latched" if event.latched else "estop_cleared"
        text = f"emergency stop {'latched' if event.latched else 'cleared'} by {event.source}"
        for link in self.links.values():
            self.event(link, None, kind, text, {"source": event.source})
        for unit in self.robot_of:
            self.publish_state(unit, changed_only=True)

    @hookimpl
    def abh3_owner(self, change: OwnerChange) -> None:
        text = f"unit {change.unit}: owner {change.old or 'nobody'} → {change.new or 'nobody'}"
        for link in self._link_of(change.unit):
            self.event(link, change.unit, "owner", text, {"old": change.old, "new": change.new})
        self.publish_state(change.unit, changed_only=True)

    @hookimpl
    def abh3_notice(self, notice: Notice) -> None:
        if notice.level >= logging.ERROR:  # what an operator must read, the fleet too
            for link in self._link_of(notice.unit):
                self.event(link, notice.unit, "notice", notice.message, {"level": notice.level})
        if notice.unit in self.robot_of:  # another host heard is said so: its state at once
            self.publish_state(notice.unit, changed_only=True)

    # ------------------------------------------------------------ what comes in

    def _lost(self, link: Link) -> None:
        """paho's thread: the broker is gone (paho reconnects on its own)."""
        if self.settings.on_broker_loss == "stop" and self.view is not None:
            self.view.emergency_stop(f"on_broker_loss: stop: {link.fleet_id} lost the broker")

    def _message(self, link: Link, message: mqtt.MQTTMessage) -> None:
        """paho's thread: a command for this robot (or all), judged and, if good, obeyed."""
        topic = message.topic
        sender = _user_property(message, "sender")
        kind = fleet.command_kind(topic, self.settings.prefix)
        needs = NEEDS.get(kind[1]) if kind is not None else "allow_estop"  # VDA: estop first
        if needs is not None and not getattr(self.settings, needs):  # unread: cheap
            self._refuse(link, topic, f"{needs} is false", sender)
            return
        try:
            commands = self._parse(link, topic, message, sender)
            if commands:  # one seq per message: a VDA message's actions share its headerId
                self.seqs.admit(f"{link.fleet_id} {topic}", commands[0])  # per robot: `all` too
        except fleet.Refused as exc:
            self._refuse(link, topic, str(exc), sender)
            return
        for command in commands:  # in order, each judged on its own
            try:
                needs = NEEDS[command.kind]
                if not getattr(self.settings, needs):
                    raise fleet.Refused(f"{command.kind} from {command.sender}: {needs} is false")
                self._obey(link, topic, command)
            except fleet.Refused as exc:
                self._refuse(link, topic, str(exc), sender)

    def _parse(
        self, link: Link, topic: str, message: mqtt.MQTTMessage, sender: str | None
    ) -> list[fleet.Command]:
        try:
            return self._read(link, topic, message, sender)
        except (RecursionError, ArithmeticError) as exc:  # deep nesting, huge numbers
            raise fleet.Refused(f"malformed: {type(exc).__name__}") from None

    def _read(
        self, link: Link, topic: str, message: mqtt.MQTTMessage, sender: str | None
    ) -> list[fleet.Command]:
        now, timeout = time.time(), self.settings.command_timeout_s
        if topic == link.topics.instant_actions:
            commands, skipped = payloads.parse_instant_actions(
                message.payload,
                now=now,
                timeout_s=timeout,
                retained=bool(message.retain),
                manufacturer=self.settings.manufacturer,
                fleet_id=link.fleet_id,
                sender_property=sender,
            )
            for why in skipped:
                self._refuse(link, topic, why, sender)
            return commands
        kind = fleet.command_kind(topic, self.settings.prefix)
        if kind is None:
            raise fleet.Refused("not a command topic of this robot")
        return [
            payloads.parse_command(
                kind[1],
                message.payload,
                now=now,
                timeout_s=timeout,
                retained=bool(message.retain),
                sender_property=sender,
            )
        ]

    def _obey(self, link: Link, topic: str, command: fleet.Command) -> None:
        view = self.view
        if view is None:
            raise fleet.Refused("the supervisor is not running yet")
        who = f"{command.sender} over MQTT ({topic})"
        data = {"topic": topic, "sender": command.sender, "seq": command.seq, **command.extra}
        if command.kind == "estop":
            view.emergency_stop(f"fleet e-stop by {who}: {command.reason}")
        elif command.kind == "estop_clear":
            view.clear_emergency_stop(f"fleet e-stop clear by {who}: {command.reason}")
        else:
            self._twist(link, command)
            return  # a twist is not news: the owner event says who drives
        log.warning("mqtt %s: %s by %s: %s", link.fleet_id, command.kind, who, command.reason)
        text = f"{command.kind} by {command.sender}: {command.reason}"
        self.event(link, None, "fleet_command", text, {"kind": command.kind, **data})

    def _twist(self, link: Link, command: fleet.Command) -> None:
        source = self.sources.get(link.robot)
        feed = source.feed if source is not None else None
        if source is None or feed is None:
            raise fleet.Refused("no fleet motion source (the inputs stopped)")
        try:  # finite (the payload's parse saw to it); beyond the limits: clamped, as at
            motor_speeds(source.robot, command.linear, command.angular)  # every entry
        except (CommandError, ValueError, ArithmeticError) as exc:
            raise fleet.Refused(f"not a twist this robot can drive: {exc}") from None
        if command.linear or command.angular:  # refused in its own answer: the event
            why = self.view.why_not_move(source.robot.name) if self.view is not None else None
            if why is not None:
                raise fleet.Refused(why)
        feed.twist(command.linear, command.angular)

    def _refuse(self, link: Link, topic: str, why: str, sender: str | None) -> None:
        if self._warn((link.fleet_id, topic)):
            log.warning("mqtt %s: refused on %s: %s", link.fleet_id, topic, why)
        second = int(time.monotonic())
        with self._lock:
            at, sent, more = self._refusals.get(link.robot, (second, 0, 0))
            if at != second:
                at, sent = second, 0
            if sent >= REFUSAL_EVENTS_PER_S:
                self._refusals[link.robot] = (at, sent, more + 1)
                return
            self._refusals[link.robot] = (at, sent + 1, 0)
        data: dict[str, Any] = {"topic": topic, "reason": why, "sender": sender}
        if more:
            data["refused_unsaid"] = more  # refusals beyond the event rate since the last
        self.event(link, None, "fleet_command_refused", f"refused on {topic}: {why}", data)

    def _say_unsaid(self) -> None:
        """The refusals beyond the event rate, counted in one event once the second is over."""
        second = int(time.monotonic())
        for robot, link in self.links.items():
            with self._lock:
                at, sent, more = self._refusals.get(robot, (second, 0, 0))
                if not more or at == second:
                    continue
                self._refusals[robot] = (at, sent, 0)
            text = f"{more} more commands refused (events at most {REFUSAL_EVENTS_PER_S}/s)"
            self.event(link, None, "fleet_command_refused", text, {"refused_unsaid": more})

    # ------------------------------------------------------------ the way out

    @hookimpl
    def abh3_stop(self) -> None:
        self._stop.set()
        if self._timer is not None:
            self._timer.join(0.5)
        for unit in self.robot_of:  # the last word on each unit: as it was left
            self.publish_state(unit)
        for link in self.links.values():
            link.say_offline()
        deadline = time.monotonic() + 1.0  # abh3_stop has 2 s
        while time.monotonic() < deadline and not all(lk.drained() for lk in self.links.values()):
            self._stop.wait(0.02)
        for link in self.links.values():
            link.close()
        for link in self.links.values():  # after every link was told: the waits overlap
            link.join()


def _foreign_news(unit: str, host: tuple[int, int] | None) -> tuple[str, dict[str, Any]]:
    """The ``foreign_host`` event's text and data: another host heard, or no longer."""
    if host is None:
        return f"unit {unit}: the other host on its drive is no longer heard", {"address": None}
    address, frames = host
    text = f"unit {unit}: another host (0x{address:02X}) on its drive ({frames} frames so far)"
    return text, {"address": address, "frames": frames}


def _user_property(message: mqtt.MQTTMessage, key: str) -> str | None:
    """An MQTT 5 user property of ``message`` (the publisher's ``sender``), or None."""
    props = getattr(message, "properties", None)
    for k, v in getattr(props, "UserProperty", None) or ():
        if k == key and isinstance(v, str) and v:
            return v
    return None
