"""The ROS 2 topics a run produces — raw frames and decoded values as CDR messages — for
whatever takes them (:class:`TopicSink`: the ``.mcap`` file, a live viewer).

Topics:

- ``/can/<bus>/tx`` and ``/can/<bus>/rx`` (``can_msgs/msg/Frame``): every frame the bus
  pump sent or received, the stop frames included — the same frames a ``.log`` holds;
- per unit, with the ROS 2 bridge's names: ``/<unit>/vel_fbk_ab``, ``/<unit>/vel_fbk_yx``
  after every DP0 reply, ``/<unit>/brd<n>_data`` for every status packet 0–6;
- per robot, ``/<robot>/odom`` (:mod:`..core.odometry`, as the ROS 2 bridge publishes it):
  at each round of its drives' DP0 replies (the command rate), its twist from their
  velocity feedback, its pose from the latest round of pulse counts carried on by the
  feedback (or the feedback alone), the pose covariance saying which; a robot of monitor
  units at each round of its pulse counts. With the robot's frame ids; a unit of a file
  without ``robots:`` is a one-drive robot named after it (``/<unit>/odom`` when its
  ``geometry.pulses_per_rev`` is known);
- ``/diagnostics`` once a second and when a level changes (:mod:`..core.diagnostics`).

Each message is encoded once (:mod:`.cdr`) and the same bytes go to every sink. What an
event needs of the live supervisor is taken on the loop (:meth:`RosTopics.capture`);
the encoding may happen later on another thread (:meth:`RosTopics.replay`: the
recorder's). This module never imports ``mcap``.
"""

from __future__ import annotations

import logging
import math
import operator
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import can

from abh3_supervisor.config.model import Config, Role
from abh3_supervisor.core.diagnostics import Health, Level, Status
from abh3_supervisor.core.odometry import Odometer, Pose, Sample, odometers, yaw_quaternion
from abh3_supervisor.core.state import Feedback
from abh3_supervisor.core.supervisor import FlagChange, Supervisor
from abh3_supervisor.protocol import frames
from abh3_supervisor.runtime.cdr import (
    ZERO_COVARIANCE,
    DiagStatus,
    FrameEncoder,
    OdomEncoder,
    diagnostic_array,
    flat_encoder,
    frame_encoder,
    odometry_encoder,
)
from abh3_supervisor.scheduler.core import FeedbackEvent, HealthEvent, StatusEvent

log = logging.getLogger(__name__)
DIAGNOSTICS_PERIOD_S = 1.0
# what capture() takes of an event: (t, unit, its feedback), (t, status event, the
# robot's feedback or None), (t, "/diagnostics", the statuses)
Captured = tuple[float, Any, Any]
SEP = "=" * 80

_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_VECTOR = "float64 x\nfloat64 y\nfloat64 z\n"
_DEPENDENCIES = {
    "std_msgs/Header": _HEADER,
    "builtin_interfaces/Time": _TIME,
    "diagnostic_msgs/DiagnosticStatus": (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\n"
        "string message\nstring hardware_id\nKeyValue[] values\n"
    ),
    "diagnostic_msgs/KeyValue": "string key\nstring value\n",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/Point": _VECTOR,
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/Twist": "Vector3 linear\nVector3 angular\n",
    "geometry_msgs/Vector3": _VECTOR,
}


def _msgdef(text: str, *dependencies: str) -> str:
    """A ``ros2msg`` schema: the type's own fields, then each type it uses."""
    parts = [text] + [f"{SEP}\nMSG: {d}\n{_DEPENDENCIES[d]}" for d in dependencies]
    return "".join(parts)


# the vendor's files (plugins/abh3_plugins/ros2/interface), as recorded: test_mcap holds them
VENDOR = {
    "Abh3Velocity": "float64 vel_ay\nfloat64 vel_bx\n",
    "Abh3Brd0": "int32 error\nint32 alarm\n",
    "Abh3Brd1": "int32 control\nint32 in_out\n",
    "Abh3Brd2": "float64 vel_cmd_ay\nfloat64 vel_cmd_bx\nfloat64 vel_fbk_ay\nfloat64 vel_fbk_bx\n",
    "Abh3Brd3": "float64 cur_cmd_ay\nfloat64 cur_cmd_bx\nfloat64 load_a\nfloat64 load_b\n",
    "Abh3Brd4": "int32 pulse_a\nint32 pulse_b\n",
    "Abh3Brd5": "float64 analog0\nfloat64 analog1\nfloat64 main_volt\nfloat64 control_volt\n",
    "Abh3Brd6": "float64 monitor0\nfloat64 monitor1\n",
}
# each vendor message's field names, split once (not per broadcast on the bus loop)
FIELDS = {name: tuple(text.split()[1::2]) for name, text in VENDOR.items()}
FRAME = "can_msgs/msg/Frame"
VELOCITY = "abh3_can_interface/msg/Abh3Velocity"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
ODOMETRY = "nav_msgs/msg/Odometry"
SCHEMAS: dict[str, str] = {
    FRAME: _msgdef(
        "std_msgs/Header header\nuint32 id\nbool is_rtr\nbool is_extended\nbool is_error\n"
        "uint8 dlc\nuint8[8] data\n",
        "std_msgs/Header",
        "builtin_interfaces/Time",
    ),
    **{f"abh3_can_interface/msg/{name}": text for name, text in VENDOR.items()},
    DIAGNOSTICS: _msgdef(
        "std_msgs/Header header\nDiagnosticStatus[] status\n",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "diagnostic_msgs/DiagnosticStatus",
        "diagnostic_msgs/KeyValue",
    ),
    ODOMETRY: _msgdef(
        "std_msgs/Header header\nstring child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "geometry_msgs/PoseWithCovariance",
        "geometry_msgs/Pose",
        "geometry_msgs/Point",
        "geometry_msgs/Quaternion",
        "geometry_msgs/TwistWithCovariance",
        "geometry_msgs/Twist",
        "geometry_msgs/Vector3",
    ),
}


class TopicSink(Protocol):
    def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        """One message: ``topic`` (``/can/b/tx`` …), ``schema`` (a key of
        :data:`SCHEMAS`), ``data`` the CDR message as rosbag2 and mcap_ros2 write it (the
        4-byte encapsulation header, little-endian), ``ns`` its wall-clock time."""


def _int32(value: int) -> int:
    return value - (1 << 32) if value & 0x80000000 else value


def _brd0(record: frames.Brd0) -> tuple[int, ...]:
    return _int32(record.error), _int32(record.alarm)


def _brd1(record: frames.Brd1) -> tuple[int, ...]:
    # 2023 sends its input word where 2021 has control (docs/ros2.md)
    first = record.control if record.control is not None else record.inputs or 0
    return _int32(first), _int32(record.io)


def _fields(name: str) -> Callable[[Any], tuple[float, ...]]:
    return operator.attrgetter(*FIELDS[name])  # two or more names: a tuple


# each broadcast's vendor message and its values in the message's order, as the bridge
# sends them (broadcast 7 is not defined: none)
BROADCASTS: dict[type, tuple[str, Callable[[Any], tuple[float, ...]]]] = {
    frames.Brd0: ("Abh3Brd0", _brd0),
    frames.Brd1: ("Abh3Brd1", _brd1),
    **{getattr(frames, f"Brd{n}"): (f"Abh3Brd{n}", _fields(f"Abh3Brd{n}")) for n in range(2, 7)},
}
ENCODERS = {f"abh3_can_interface/msg/{name}": flat_encoder(text) for name, text in VENDOR.items()}


class RosTopics(can.Listener):
    """Frames (a bus listener) and supervisor events (:meth:`observe`) in, CDR messages
    out to every sink, all on the loop thread. Each message is encoded once, by an
    encoder made once per message type and constant frame id (:mod:`.cdr`), and each
    topic's name is made once: the loop builds no dicts per message.

    A sink that raises is dropped — it gets no more messages, and the failure is logged
    once and kept in :attr:`failures` — and the others get this message and the ones
    after it: a full disk under the recording does not stop a live view, nor a live view's
    fault the recording. A sink that must report its own failure (the ``.mcap`` file,
    through :class:`~.recorder.GuardedRecorder`) keeps it and raises it itself.
    :attr:`sinks` is a list: a live view may append its sink to it (on the loop thread)."""

    def __init__(self, config: Config, sinks: Sequence[TopicSink]) -> None:
        self.sinks = list(sinks)
        self.failures: list[tuple[TopicSink, Exception]] = []
        self.bus_of = {cfg.channel: name for name, cfg in config.buses.items()}
        self.config = config
        self.health: Health | None = None
        self._sup: Supervisor | None = None  # read on the loop only (capture)
        self.odometry: dict[str, list[Odometer]] = {}  # unit → the robots it is a drive of
        for odometer in odometers(config):
            for unit in odometer.units:
                self.odometry.setdefault(unit, []).append(odometer)
        self.offset_ns = 0  # wall clock minus the supervisor's clock
        self._next_diagnostics = -math.inf
        self._levels: dict[str, Level] = {}
        # made at first use: (channel, is_rx) → topic, encoder; unit → its two topics …
        self._frames: dict[tuple[object, bool], tuple[str, FrameEncoder]] = {}
        self._feedback_topics: dict[str, tuple[str, str]] = {}
        self._status_topics: dict[tuple[str, int], str] = {}
        self._odom: dict[str, tuple[str, OdomEncoder]] = {}
        # a robot whose drives are all commanded is sampled at each round of their DP0
        # replies (core/odometry.py, as the bridge); a monitor robot at its pulse counts
        commanded = {n for n, u in config.units.items() if u.role is Role.COMMAND}
        self._live = {
            odometer.robot.name: set(odometer.units) <= commanded
            for odos in self.odometry.values()
            for odometer in odos
        }
        # unit → every wheel's drive of the robots it is a drive of (odometry's twist)
        self._wheels = {
            unit: tuple(dict.fromkeys(u for o in odos for u in o.robot.units))
            for unit, odos in self.odometry.items()
        }

    def _emit(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        for sink in self.sinks:
            try:
                sink.write(topic, schema, data, ns)
            except Exception as exc:
                self._drop(sink, exc)

    def _drop(self, sink: TopicSink, exc: Exception) -> None:
        # a new list: the loop in _emit goes on over the old one, to the sinks after it
        self.sinks = [s for s in self.sinks if s is not sink]
        self.failures.append((sink, exc))
        log.warning("%s failed (%s): it gets no more topics", type(sink).__name__, exc)

    # ------------------------------------------------------------ raw frames

    def on_message_received(self, msg: can.Message) -> None:
        route = self._frames.get((msg.channel, msg.is_rx))
        if route is None:
            route = self._frame_route(msg.channel, msg.is_rx)
        topic, encode = route
        ns = int(msg.timestamp * 1e9)
        sec, nanosec = divmod(ns, 1_000_000_000)
        data = encode(
            sec, nanosec, msg.arbitration_id, msg.is_remote_frame, msg.is_extended_id,
            msg.is_error_frame, msg.dlc, msg.data,
        )  # fmt: skip
        self._emit(topic, FRAME, data, ns)

    def _frame_route(self, channel: object, rx: bool) -> tuple[str, FrameEncoder]:
        bus = self.bus_of.get(str(channel), str(channel))
        route = f"/can/{bus}/{'rx' if rx else 'tx'}", frame_encoder(bus)
        self._frames[channel, rx] = route
        return route

    # ------------------------------------------------------------ decoded values

    def attach(self, sup: Supervisor, clock: Callable[[], float]) -> None:
        """Produce ``sup``'s decoded values; ``clock`` is its clock (the loop's)."""
        self.health = Health(sup)
        self._sup = sup
        self.offset_ns = time.time_ns() - int(clock() * 1e9)

    def observe(self, event: object) -> None:
        """A supervisor event, on the loop thread: captured and written at once."""
        for item in self.capture(event):
            self.replay(item)

    def capture(self, event: object) -> list[Captured]:
        """On the loop thread: what of ``event`` the topics need, as values that do not
        change — the drive's feedback it brought, the robot's feedback beside a pulse
        count, the diagnostics when due — for :meth:`replay` to encode and write on any
        thread later (the recorder's). The live supervisor is read here only."""
        t = getattr(event, "t", None)
        if t is None:
            return []
        units = self._sup.units if self._sup is not None else {}
        out: list[Captured] = []
        if isinstance(event, FeedbackEvent):
            state = units.get(event.unit)
            fbk = state.feedback if state is not None else None
            if fbk is not None and not isinstance(event.reply, frames.Unknown):
                out.append((t, event.unit, fbk))
        elif isinstance(event, StatusEvent):
            robots = None
            if isinstance(event.record, frames.Brd4) and event.unit in self.odometry and units:
                robots = {u: units[u].feedback for u in self._wheels[event.unit]}
            out.append((t, event, robots))
        # a level follows only online, error and alarm (the rate is caught by the period):
        # a 2023 drive's busy bits change its control word on every reply
        levelled = isinstance(event, HealthEvent) or (
            isinstance(event, FlagChange) and event.word in ("error", "alarm")
        )
        if self.health is not None and (t >= self._next_diagnostics or levelled):
            statuses = self.health.statuses(t)
            levels = {s.name: s.level for s in statuses}
            if t >= self._next_diagnostics or levels != self._levels:
                self._levels, self._next_diagnostics = levels, t + DIAGNOSTICS_PERIOD_S
                out.append((t, "/diagnostics", tuple(statuses)))
        return out

    def replay(self, item: Captured) -> None:
        """Encode and write what :meth:`capture` took (any thread, in capture's order)."""
        t, what, values = item
        ns = self.offset_ns + int(t * 1e9)
        if isinstance(what, str):
            if what == "/diagnostics":
                sec, nanosec = divmod(ns, 1_000_000_000)
                data = diagnostic_array(sec, nanosec, "", [_diag(s) for s in values])
                self._emit("/diagnostics", DIAGNOSTICS, data, ns)
            else:
                self._feedback(what, values, ns)
                for odometer in self.odometry.get(what, ()):
                    if self._live[odometer.robot.name]:  # a round of replies: a sample
                        sample = odometer.feedback(what, values)
                        if sample is not None:
                            self._odom_sample(odometer, sample, ns)
        else:
            self._status(what, ns, values)

    def _feedback(self, u: str, fbk: Feedback, ns: int) -> None:
        topics = self._feedback_topics.get(u)
        if topics is None:
            topics = self._feedback_topics[u] = (f"/{u}/vel_fbk_ab", f"/{u}/vel_fbk_yx")
        self._emit(topics[0], VELOCITY, _velocity(fbk.vel_a, fbk.vel_b), ns)
        self._emit(topics[1], VELOCITY, _velocity(fbk.vel_y, fbk.vel_x), ns)

    def _status(
        self, event: StatusEvent, ns: int, feedback: dict[str, Feedback | None] | None
    ) -> None:
        record = event.record
        named = BROADCASTS.get(type(record))
        if named is not None:
            name, values = named
            key = (event.unit, event.packet)
            topic = self._status_topics.get(key)
            if topic is None:
                topic = self._status_topics[key] = f"/{event.unit}/brd{event.packet}_data"
            schema = f"abh3_can_interface/msg/{name}"
            self._emit(topic, schema, ENCODERS[schema](*values(record)), ns)
        if isinstance(record, frames.Brd4):
            for odometer in self.odometry.get(event.unit, ()):
                pose = odometer.pulses(event.unit, record.pulse_a, record.pulse_b, event.t)
                # a robot of drives we command is sampled at each round of its replies
                # (above); a monitor robot's pose comes with its every wheel's counts
                live = self._live[odometer.robot.name]
                if pose is not None and feedback is not None and not live:
                    linear, angular = odometer.twist({u: feedback[u] for u in odometer.units})
                    covariance = odometer.pose_covariance("pulses")
                    self._odometry(odometer, pose, linear, angular, covariance, ns)

    def _odom_sample(self, odometer: Odometer, sample: Sample, ns: int) -> None:
        self._odometry(
            odometer,
            sample.pose,
            sample.linear_x,
            sample.angular_z,
            sample.pose_covariance,
            ns,
            sample.twist_covariance,
        )

    def _odometry(
        self,
        odometer: Odometer,
        pose: Pose,
        linear: float,
        angular: float,
        pose_covariance: Sequence[float],
        ns: int,
        twist_covariance: Sequence[float] = ZERO_COVARIANCE,
    ) -> None:
        robot = odometer.robot
        route = self._odom.get(robot.name)
        if route is None:
            route = f"/{robot.name}/odom", odometry_encoder(robot.frame_id, robot.child_frame_id)
            self._odom[robot.name] = route
        topic, encode = route
        qx, qy, qz, qw = yaw_quaternion(pose.yaw)
        sec, nanosec = divmod(ns, 1_000_000_000)
        data = encode(
            sec, nanosec, pose.x, pose.y, qx, qy, qz, qw, linear, angular,
            pose_covariance, twist_covariance,
        )  # fmt: skip
        self._emit(topic, ODOMETRY, data, ns)


_velocity = ENCODERS[VELOCITY]


def _diag(s: Status) -> DiagStatus:
    return int(s.level), s.name, s.message, s.hardware_id, s.values
