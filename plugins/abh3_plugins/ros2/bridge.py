"""``ros2``: the vendor sample's whole ROS 2 interface, per unit, with or without ROS.

Per unit, under ``<namespace>/<unit>/`` (every name remappable, see settings.py):

- command node: ``vel_cmd``, ``cur_cmd``, ``inp_data`` and the ``inp_service`` command
  language — only with ``allow_commands: true``; ``vel_fbk_ab``/``vel_fbk_yx`` after
  every exchange;
- status node: ``brd_num`` asks for a packet of the unit's mask; ``brd0_data`` …
  ``brd6_data`` for the mask, also on the scheduler's own polling (``status: poll``);
- conversion node: ``xa``/``yx``/``ab`` → ``xa_yx``, ``xa_ab``, ``yx_xa``, ``yx_ab``,
  ``ab_yx``, ``ab_xa`` with the unit's geometry.

And what ROS users expect today, per robot (robot.py): ``cmd_vel`` (with
``allow_commands``) driving the whole robot and ``odom`` from every wheel's pulse counts,
under ``<namespace>/<robot>/``. A unit of a file without ``robots:`` is a one-drive robot
named after it: its pair is the unit's, with the names and behaviour of before.

Motion commands go through the input arbitration as one source per unit (and one per
declared robot, for its ``cmd_vel``): silence longer than ``command_timeout_ms`` means
zero, like every other source. Every incoming value is checked (finite, within the
protocol's range) before it can reach a drive.
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
from collections.abc import Callable
from typing import Any

from abh3_plugins.ros2.diagnostics import (
    TOPIC,
    DiagnosticsPublisher,
    DiagnosticsThread,
    ViewHealth,
)
from abh3_plugins.ros2.robot import RobotBridge, RobotTopics
from abh3_plugins.ros2.settings import Settings, parse, schema
from abh3_plugins.ros2.transport import Transport, decide, open_transport
from abh3_plugins.ros2.values import Guard, twist_values, within
from abh3_plugins.ros2.values import Refused as Refused  # the bridge's names, as before
from abh3_plugins.ros2.values import twist as twist
from abh3_supervisor.plugin_api import (
    RESPONSE_INVALID,
    Config,
    Feedback,
    FlagChange,
    InputFeed,
    InputSource,
    Role,
    Section,
    SupervisorView,
    UnitView,
    frames,
    from_geometry,
    hookimpl,
    kinematics,
)

log = logging.getLogger(__name__)
ABH3_API_VERSION = "1.0"  # the plugin API (abh3_supervisor.plugin_api) this is written for
MAX_COMMAND_TEXT = 256  # longer than any command of the language


def _int32(value: int) -> int:
    """Flag words go out as the vendor's int32 fields: the same 32 bits, signed."""
    return value - (1 << 32) if value & 0x80000000 else value


# packets 2-6: the vendor's message and its fields, which the decoded records share
SAME_FIELDS: dict[type, tuple[str, tuple[str, ...]]] = {
    frames.Brd2: ("Abh3Brd2", ("vel_cmd_ay", "vel_cmd_bx", "vel_fbk_ay", "vel_fbk_bx")),
    frames.Brd3: ("Abh3Brd3", ("cur_cmd_ay", "cur_cmd_bx", "load_a", "load_b")),
    frames.Brd4: ("Abh3Brd4", ("pulse_a", "pulse_b")),
    frames.Brd5: ("Abh3Brd5", ("analog0", "analog1", "main_volt", "control_volt")),
    frames.Brd6: ("Abh3Brd6", ("monitor0", "monitor1")),
}


def brd_message(msg: Any, record: frames.Broadcast) -> Any:
    """The vendor's ``Abh3Brd<n>`` message for a decoded broadcast, or None (packet 7)."""
    if isinstance(record, frames.Brd0):
        return msg.Abh3Brd0(error=_int32(record.error), alarm=_int32(record.alarm))
    if isinstance(record, frames.Brd1):
        # 2021: control + I/O; 2023 sends the input word where control was
        first = record.control if record.control is not None else record.inputs or 0
        return msg.Abh3Brd1(control=_int32(first), in_out=_int32(record.io))
    same = SAME_FIELDS.get(type(record))
    if same is None:
        return None  # broadcast 7 is not defined: nothing to publish
    name, fields = same
    return getattr(msg, name)(**{f: getattr(record, f) for f in fields})


class UnitBridge(InputSource):
    """One unit's topics and service; also its input source in the arbitration.

    ``one_drive``: the unit is a one-drive robot of its own (its ``geometry``), so it also
    carries that robot's ``cmd_vel`` and ``odom``; False for a wheel drive of a declared
    robot, whose pair is the robot's (:class:`RobotBridge`).
    """

    def __init__(
        self, unit: UnitView, t: Transport, settings: Settings, *, one_drive: bool = True
    ) -> None:
        super().__init__(
            f"ros2:{unit.name}", (unit.name,), settings.priority, settings.command_timeout
        )
        self.unit, self.t, self.settings = unit, t, settings
        self.cfg = unit.cfg
        self.feed: InputFeed | None = None
        self.requested: set[int] = set()  # brd_num packets awaiting their answer
        self._guarded = Guard(unit.name)
        msg = t.msg
        self.fbk_ab = t.publisher(self.name_of("vel_fbk_ab"), msg.Abh3Velocity)
        self.fbk_yx = t.publisher(self.name_of("vel_fbk_yx"), msg.Abh3Velocity)
        packets = self.cfg.broadcast.packets
        # only the mask's publishers, as the seed's status node
        self.brd = {
            n: t.publisher(self.name_of(f"brd{n}_data"), _brd_type(msg, n)) for n in packets
        }
        self.mask = set(packets)
        t.subscribe(self.name_of("brd_num"), msg.Int32, self._guarded("brd_num", self.on_brd_num))
        commands = settings.allow_commands and self.cfg.role is Role.COMMAND
        self.robot: RobotTopics | None = None
        if one_drive:
            self.robot = RobotTopics(
                from_geometry(unit.name, self.cfg.geometry),
                t,
                settings,
                states={unit.name: unit},
                feed=lambda: self.feed,
                commands=commands,
                frame_ids=(settings.odom_frame, settings.base_frame),
                geometry=self.cfg.geometry,
                guard=self._guarded,
            )
        if settings.conversion:
            self._conversion()
        if commands:
            self._commands()

    def name_of(self, name: str) -> str:
        return self.settings.name(self.unit.name, name)

    # ------------------------------------------------------------ input source

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None  # from now on every incoming command is dropped

    # ------------------------------------------------------------ incoming

    def on_brd_num(self, m: Any) -> None:
        if m.data not in self.mask:  # as the seed: numbers outside 0–6 or the mask
            raise Refused(f"packet {m.data} is not in the unit's mask {sorted(self.mask)}")
        feed = self.feed
        if feed is not None:
            self.requested.add(m.data)
            feed.request_status(m.data)

    def _commands(self) -> None:
        t, msg = self.t, self.t.msg

        # one rule at every entry: a number that is not finite is refused; a finite one
        # beyond the unit's limits or the wire's range is clamped by the supervisor, both
        # axes alike, and said (docs/safety.md, "The robot decision")
        def vel_cmd(m: Any) -> None:
            within(None, m.vel_ay, m.vel_bx)
            feed = self.feed  # None once the inputs stopped
            if feed is not None:
                feed.velocity(m.vel_ay, m.vel_bx)

        def cur_cmd(m: Any) -> None:
            within(None, m.cur_ay, m.cur_bx)
            feed = self.feed  # None once the inputs stopped
            if feed is not None:
                feed.current(m.cur_ay, m.cur_bx)

        def inp_data(m: Any) -> None:
            if undefined := self.unit.layout.undefined(m.data & m.mask):
                raise Refused(
                    f"bits 0x{undefined:08X} are not defined for protocol {self.cfg.protocol}"
                )
            feed = self.feed  # None once the inputs stopped
            if feed is not None:
                feed.inputs(m.data, m.mask)

        for name, typ, handle in (
            ("vel_cmd", msg.Abh3Velocity, vel_cmd),
            ("cur_cmd", msg.Abh3Current, cur_cmd),
            ("inp_data", msg.Abh3Input, inp_data),
        ):
            t.subscribe(self.name_of(name), typ, self._guarded(name, handle))
        t.serve(self.name_of("inp_service"), self.inp_service)

    def inp_service(self, command: str) -> concurrent.futures.Future[str]:
        feed = self.feed
        if feed is None or len(command) > MAX_COMMAND_TEXT:
            done: concurrent.futures.Future[str] = concurrent.futures.Future()
            done.set_result(RESPONSE_INVALID)
            return done
        return feed.command(command)

    def _conversion(self) -> None:
        t, msg, g = self.t, self.t.msg, self.cfg.geometry
        out = {
            name: t.publisher(self.name_of(name), typ)
            for name, typ in (
                ("xa_yx", msg.Abh3Velocity),
                ("xa_ab", msg.Abh3Velocity),
                ("yx_xa", msg.Twist),
                ("yx_ab", msg.Abh3Velocity),
                ("ab_yx", msg.Abh3Velocity),
                ("ab_xa", msg.Twist),
            )
        }

        def velocity(ay: float, bx: float) -> Any:
            return msg.Abh3Velocity(vel_ay=ay, vel_bx=bx)

        def from_xa(m: Any) -> None:
            y, x = kinematics.twist_to_yx(*twist_values(m), g)
            out["xa_yx"](velocity(y, x))
            out["xa_ab"](velocity(*kinematics.yx_to_ab(y, x)))

        def from_yx(m: Any) -> None:
            within(None, m.vel_ay, m.vel_bx)
            out["yx_xa"](twist(msg, *kinematics.yx_to_twist(m.vel_ay, m.vel_bx, g)))
            out["yx_ab"](velocity(*kinematics.yx_to_ab(m.vel_ay, m.vel_bx)))

        def from_ab(m: Any) -> None:
            within(None, m.vel_ay, m.vel_bx)
            out["ab_yx"](velocity(*kinematics.ab_to_yx(m.vel_ay, m.vel_bx)))
            out["ab_xa"](twist(msg, *kinematics.ab_to_twist(m.vel_ay, m.vel_bx, g)))

        t.subscribe(self.name_of("xa"), msg.Twist, self._guarded("xa", from_xa))
        t.subscribe(self.name_of("yx"), msg.Abh3Velocity, self._guarded("yx", from_yx))
        t.subscribe(self.name_of("ab"), msg.Abh3Velocity, self._guarded("ab", from_ab))

    # ------------------------------------------------------------ outgoing

    def feedback(self, feedback: Feedback) -> None:
        msg = self.t.msg
        self.fbk_ab(msg.Abh3Velocity(vel_ay=feedback.vel_a, vel_bx=feedback.vel_b))
        self.fbk_yx(msg.Abh3Velocity(vel_ay=feedback.vel_y, vel_bx=feedback.vel_x))
        if self.robot is not None:
            self.robot.feedback(self.unit.name, feedback)

    def status(self, packet: int, record: frames.Broadcast, t: float | None = None) -> None:
        asked = packet in self.requested
        self.requested.discard(packet)
        publish = self.brd.get(packet)
        if publish is not None and (asked or self.settings.status == "poll"):
            message = brd_message(self.t.msg, record)
            if message is not None:
                publish(message)
        if self.robot is not None:
            self.robot.status(self.unit.name, record, t)


def _brd_type(msg: Any, n: int) -> type:
    return getattr(msg, f"Abh3Brd{n}")  # type: ignore[no-any-return]


class Ros2Plugin:
    def __init__(self) -> None:
        self.settings = Settings()
        self.transport: Transport | None = None
        self.units: dict[str, UnitBridge] = {}
        self.robots: dict[str, RobotBridge] = {}  # the declared robots' cmd_vel and odom
        self._robots_of: dict[str, list[RobotBridge]] = {}  # unit → its declared robot
        self.diagnostics: DiagnosticsPublisher | None = None
        self._diagnostics_thread: DiagnosticsThread | None = None

    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        return schema()

    @hookimpl
    def abh3_configure(self, section: Section, config: Config) -> None:
        self.settings = parse(section, config)
        kind = self.settings.transport
        chosen, why = decide(kind)
        if chosen is None:
            section.error("transport", why)
        elif kind == "auto":  # `abh3 check` and `abh3 run` both say which, and why
            where = section.src.line((*section.path, "transport"))
            log.info(
                "%s:%d: plugins.ros2.transport: auto → %s: %s", section.src.file, where, chosen, why
            )

    @hookimpl
    def abh3_start(self, supervisor: SupervisorView) -> None:
        t = self.transport = open_transport(self.settings)
        declared = [r for r in supervisor.config.robots.values() if not r.implicit]
        wheels = {u for r in declared for u in r.units}
        for name, unit in supervisor.units.items():
            self.units[name] = UnitBridge(unit, t, self.settings, one_drive=name not in wheels)
        for robot in declared:
            bridge = self.robots[robot.name] = RobotBridge(
                robot, t, self.settings, supervisor.units
            )
            for unit_name in robot.units:
                self._robots_of.setdefault(unit_name, []).append(bridge)
        publish = t.publisher(TOPIC, t.msg.DiagnosticArray)
        self.diagnostics = DiagnosticsPublisher(
            ViewHealth(supervisor), publish, t.msg, self.settings.diagnostics_hz
        )
        if self.settings.diagnostics_hz > 0:  # 0: on changes only, from the hooks below
            self._diagnostics_thread = DiagnosticsThread(self.diagnostics)
        t.start()
        if self._diagnostics_thread is not None:
            self._diagnostics_thread.start()
        log.log(
            logging.WARNING if self.settings.allow_commands else logging.INFO,
            "ros2: %d unit(s) on domain %d over %s; commands from ROS 2 %s",
            len(self.units),
            self.settings.domain_id,
            type(t).__name__,
            "ALLOWED" if self.settings.allow_commands else "off (allow_commands: false)",
        )
        for robot in declared:
            own, named = self.settings.of(robot.name), self.settings.name
            topics = [named(robot.name, "cmd_vel"), named(robot.name, "odom")]
            if own.odom_tf:
                topics.append(self.settings.tf_name(robot.name))
            if own.joint_states:
                topics.append(named(robot.name, "joint_states"))
                if self.settings.allow_commands:
                    topics.append(named(robot.name, "joint_commands"))
            log.info(
                "ros2: robot %s (%s): %s", robot.name, ", ".join(robot.units), ", ".join(topics)
            )

    @hookimpl
    def abh3_input_sources(self, register: Callable[[InputSource], None]) -> None:
        for bridge in self.units.values():
            register(bridge)  # brd_num needs the feed too, so always registered
        if self.settings.allow_commands:
            for robot in self.robots.values():
                register(robot)

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback) -> None:
        bridge = self.units.get(unit)  # none if the transport failed to start (logged)
        if bridge is not None:
            bridge.feedback(feedback)
        for robot in self._robots_of.get(unit, ()):
            robot.feedback(unit, feedback)

    @hookimpl
    def abh3_status(
        self, unit: str, packet: int, record: frames.Broadcast, t: float | None = None
    ) -> None:
        bridge = self.units.get(unit)
        if bridge is not None:
            bridge.status(packet, record, t)
        for robot in self._robots_of.get(unit, ()):
            robot.status(unit, record, t)

    @hookimpl
    def abh3_health(self) -> None:
        if self.diagnostics is not None:  # STALE (or back) at once, not a period later
            self.diagnostics.changed(time.monotonic())

    @hookimpl
    def abh3_flags(self, change: FlagChange) -> None:
        # any word: an error or alarm sets a unit's level, and what a drive reports
        # switched on (SERVO, START) its robot's (ready or not): published at once when a
        # level changed (changed() compares), not a period later
        if self.diagnostics is not None:
            self.diagnostics.changed(time.monotonic())

    @hookimpl
    def abh3_stop(self) -> None:
        if self._diagnostics_thread is not None:
            self._diagnostics_thread.close()
            self._diagnostics_thread = None
        if self.transport is not None:
            self.transport.close()
            self.transport = None
