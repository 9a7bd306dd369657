"""``--record run.mcap``: the raw CAN frames and the decoded values as ROS 2 messages.

An MCAP file with the ``ros2`` profile, CDR messages and ``ros2msg`` schemas, as rosbag2
writes it, so ``ros2 bag info/play``, Foxglove and rosbags open it. Topics:

- ``/can/<bus>/tx`` and ``/can/<bus>/rx`` (``can_msgs/msg/Frame``): every frame the bus
  pump sent or received, the stop frames included — the same frames a ``.log`` holds;
- per unit, with the ROS 2 bridge's names: ``/<unit>/vel_fbk_ab``, ``/<unit>/vel_fbk_yx``
  after every DP0 reply, ``/<unit>/brd<n>_data`` for every status packet 0–6;
- per robot, ``/<robot>/odom`` from every wheel's pulse counts and velocity feedback
  (:mod:`..core.odometry`) when every wheel's pulses_per_rev is known, with the robot's
  frame ids; a unit of a file without ``robots:`` is a one-drive robot named after it
  (``/<unit>/odom`` when its ``geometry.pulses_per_rev`` is known, as before robots);
- ``/diagnostics`` once a second and when a level changes (:mod:`..core.diagnostics`).

Written on the event loop as frames and events arrive. The chunk in progress is closed,
compressed and written at every :meth:`McapRecording.flush` (every ``FLUSH_S``, see
:mod:`.recorder`) or at ``CHUNK_BYTES``, whichever comes first, so a ``kill -9`` loses at
most the last ``FLUSH_S``. What it leaves has no summary (index, statistics, footer):
readers that go through the file from the start read it (the mcap library's
``StreamReader`` and ``NonSeekingReader``, ``abh3 decode``); those that seek to the
summary first need ``mcap recover`` to rewrite it. A write that fails (disk full) ends the
recording through :class:`~.recorder.GuardedRecorder`, never the run. ``mcap`` is imported
only here, only when an ``.mcap`` recording is asked for.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Generator
from pathlib import Path
from typing import IO, Any

import can

from abh3_supervisor.config.model import Config
from abh3_supervisor.core.diagnostics import Health, Level, Status
from abh3_supervisor.core.odometry import Odometer, Pose, odometers, yaw_quaternion
from abh3_supervisor.core.supervisor import FlagChange, Supervisor
from abh3_supervisor.errors import BusOpenError
from abh3_supervisor.protocol import frames
from abh3_supervisor.runtime.mcap_index import spill_chunk_indexes
from abh3_supervisor.scheduler.core import FeedbackEvent, HealthEvent, StatusEvent

CHUNK_BYTES = 256 << 10  # an upper bound: the flush closes a chunk sooner
DIAGNOSTICS_PERIOD_S = 1.0
INSTALL_HINT = "pip install 'abh3-supervisor[mcap]'"
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
SCHEMAS = {
    "can_msgs/msg/Frame": _msgdef(
        "std_msgs/Header header\nuint32 id\nbool is_rtr\nbool is_extended\nbool is_error\n"
        "uint8 dlc\nuint8[8] data\n",
        "std_msgs/Header",
        "builtin_interfaces/Time",
    ),
    **{f"abh3_can_interface/msg/{name}": text for name, text in VENDOR.items()},
    "diagnostic_msgs/msg/DiagnosticArray": _msgdef(
        "std_msgs/Header header\nDiagnosticStatus[] status\n",
        "std_msgs/Header",
        "builtin_interfaces/Time",
        "diagnostic_msgs/DiagnosticStatus",
        "diagnostic_msgs/KeyValue",
    ),
    "nav_msgs/msg/Odometry": _msgdef(
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
ZERO36 = [0.0] * 36


def _int32(value: int) -> int:
    return value - (1 << 32) if value & 0x80000000 else value


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def brd_fields(record: frames.Broadcast) -> tuple[str, dict[str, Any]] | None:
    """The vendor message and its fields for a decoded broadcast, as the bridge sends it."""
    if isinstance(record, frames.Brd0):
        return "Abh3Brd0", {"error": _int32(record.error), "alarm": _int32(record.alarm)}
    if isinstance(record, frames.Brd1):
        # 2023 sends its input word where 2021 has control (docs/ros2.md)
        first = record.control if record.control is not None else record.inputs or 0
        return "Abh3Brd1", {"control": _int32(first), "in_out": _int32(record.io)}
    name = f"Abh3Brd{type(record).__name__.removeprefix('Brd')}"
    if name not in VENDOR or not hasattr(record, "__dataclass_fields__"):
        return None  # broadcast 7 is not defined
    return name, {k: getattr(record, k) for k in FIELDS[name]}


def open_mcap(path: Path, config: Config) -> McapRecording:
    """The recording, or a BusOpenError a user can act on (before any bus opens)."""
    try:
        import mcap_ros2.writer  # noqa: F401  (only to say now if it is missing)
    except ImportError as exc:
        raise BusOpenError(
            f"--record {path}: an .mcap recording needs the mcap libraries: {INSTALL_HINT}"
            f" ({exc.name or exc} is not installed)"
        ) from exc
    try:
        stream = open(path, "wb")  # noqa: SIM115  (closed in stop())
    except OSError as exc:
        raise BusOpenError(f"--record {path}: cannot write: {exc.strerror}") from exc
    return McapRecording(stream, config, index_dir=path.parent)


class McapRecording(can.Listener):
    def __init__(self, stream: IO[bytes], config: Config, index_dir: Path | None = None) -> None:
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer

        self.stream = stream
        self.writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        # what would grow with the length, on disk (None: kept by the writer, in memory)
        self.index = (
            None if index_dir is None else spill_chunk_indexes(self.writer._writer, index_dir)
        )
        self.schemas = {name: self.writer.register_msgdef(name, t) for name, t in SCHEMAS.items()}
        self.bus_of = {cfg.channel: name for name, cfg in config.buses.items()}
        self.config = config
        self.counts: dict[str, int] = {}
        self.health: Health | None = None
        self.odometry: dict[str, list[Odometer]] = {}  # unit → the robots it is a drive of
        for odometer in odometers(config):
            for unit in odometer.units:
                self.odometry.setdefault(unit, []).append(odometer)
        self.offset_ns = 0  # wall clock minus the supervisor's clock
        self._clock: Callable[[], float] = time.monotonic
        self._next_diagnostics = -math.inf
        self._levels: dict[str, Level] = {}
        self._finished = False
        self.broken = False

    def write(self, topic: str, schema: str, message: dict[str, Any], ns: int) -> None:
        self.counts[topic] = sequence = self.counts.get(topic, 0) + 1
        try:
            self.writer.write_message(topic, self.schemas[schema], message, ns, ns, sequence)
        except Exception:
            self.broken = True  # disk full: what is on disk stays readable, nothing more
            raise

    # ------------------------------------------------------------ raw frames

    def on_message_received(self, msg: can.Message) -> None:
        bus = self.bus_of.get(str(msg.channel), str(msg.channel))
        ns = int(msg.timestamp * 1e9)
        data = bytes(msg.data) + bytes(8 - len(msg.data))
        frame = {
            "header": {"stamp": _stamp(ns), "frame_id": bus},
            "id": msg.arbitration_id,
            "is_rtr": msg.is_remote_frame,
            "is_extended": msg.is_extended_id,
            "is_error": msg.is_error_frame,
            "dlc": msg.dlc,
            "data": list(data[:8]),
        }
        self.write(f"/can/{bus}/{'rx' if msg.is_rx else 'tx'}", "can_msgs/msg/Frame", frame, ns)

    # ------------------------------------------------------------ decoded values

    def attach(self, sup: Supervisor, clock: Callable[[], float]) -> None:
        """Record ``sup``'s decoded values; ``clock`` is its clock (the loop's)."""
        self.health = Health(sup)
        self._clock = clock
        self.offset_ns = time.time_ns() - int(clock() * 1e9)

    def observe(self, event: object) -> None:
        """A supervisor event (on the loop thread)."""
        t = getattr(event, "t", None)
        if t is None:
            return
        ns = self.offset_ns + int(t * 1e9)
        if isinstance(event, FeedbackEvent) and not isinstance(event.reply, frames.Unknown):
            self._feedback(event, ns)
        elif isinstance(event, StatusEvent):
            self._status(event, ns)
        # a level follows only online, error and alarm (the rate is caught by the period):
        # a 2023 drive's busy bits change its control word on every reply
        levelled = isinstance(event, HealthEvent) or (
            isinstance(event, FlagChange) and event.word in ("error", "alarm")
        )
        self._diagnostics(t, ns, levelled)

    def _feedback(self, event: FeedbackEvent, ns: int) -> None:
        assert self.health is not None
        fbk = self.health.sup.units[event.unit].feedback
        if fbk is None:
            return
        u = event.unit
        self.write(
            f"/{u}/vel_fbk_ab", "abh3_can_interface/msg/Abh3Velocity",
            {"vel_ay": fbk.vel_a, "vel_bx": fbk.vel_b}, ns,
        )  # fmt: skip
        self.write(
            f"/{u}/vel_fbk_yx", "abh3_can_interface/msg/Abh3Velocity",
            {"vel_ay": fbk.vel_y, "vel_bx": fbk.vel_x}, ns,
        )  # fmt: skip

    def _status(self, event: StatusEvent, ns: int) -> None:
        if isinstance(event.record, frames.Unknown):
            return
        named = brd_fields(event.record)
        if named is not None:
            name, fields = named
            topic = f"/{event.unit}/brd{event.packet}_data"
            self.write(topic, f"abh3_can_interface/msg/{name}", fields, ns)
        record = event.record
        if isinstance(record, frames.Brd4):
            for odometer in self.odometry.get(event.unit, ()):
                pose = odometer.pulses(event.unit, record.pulse_a, record.pulse_b, event.t)
                if pose is not None:  # every unit of the robot reported anew
                    self._odom(odometer, pose, ns)

    def _odom(self, odometer: Odometer, pose: Pose, ns: int) -> None:
        assert self.health is not None
        units = self.health.sup.units
        robot = odometer.robot
        linear, angular = odometer.twist({u: units[u].feedback for u in robot.units})
        qx, qy, qz, qw = yaw_quaternion(pose.yaw)
        odom = {
            "header": {"stamp": _stamp(ns), "frame_id": robot.frame_id},
            "child_frame_id": robot.child_frame_id,
            "pose": {
                "pose": {
                    "position": {"x": pose.x, "y": pose.y, "z": 0.0},
                    "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
                },
                "covariance": ZERO36,
            },
            "twist": {
                "twist": {
                    "linear": {"x": linear, "y": 0.0, "z": 0.0},
                    "angular": {"x": 0.0, "y": 0.0, "z": angular},
                },
                "covariance": ZERO36,
            },
        }
        self.write(f"/{robot.name}/odom", "nav_msgs/msg/Odometry", odom, ns)

    def _diagnostics(self, now: float, ns: int, changed: bool) -> None:
        if self.health is None or (now < self._next_diagnostics and not changed):
            return
        statuses = self.health.statuses(now)
        levels = {s.name: s.level for s in statuses}
        if now < self._next_diagnostics and levels == self._levels:
            return
        self._levels, self._next_diagnostics = levels, now + DIAGNOSTICS_PERIOD_S
        array = {"header": {"stamp": _stamp(ns), "frame_id": ""}, "status": _statuses(statuses)}
        self.write("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", array, ns)

    # ------------------------------------------------------------ the end

    def flush(self) -> None:
        """Close the chunk in progress and hand the file's bytes to the OS."""
        if self._finished:
            return
        mcap: Any = self.writer._writer  # mcap_ros2 keeps the mcap Writer here
        if hasattr(mcap, "flush"):  # recent mcap: closes the chunk, flushes the stream
            mcap.flush()
            return
        mcap._Writer__finalize_chunk()  # older mcap: the same, by its private name
        self.stream.flush()

    def stop(self) -> None:
        """Index and close the file (after the stop frames)."""
        if self._finished:
            return
        self._finished = True
        try:
            if self.broken:  # after a failed write: keep the whole chunks already written
                with contextlib.suppress(OSError):
                    self.stream.close()
                return
            try:
                self.writer.finish()  # type: ignore[no-untyped-call]
            finally:
                self.stream.close()
        finally:
            if self.index is not None:
                self.index.close()  # unlinked already: closing frees its space


def _statuses(statuses: list[Status]) -> list[dict[str, Any]]:
    return [
        {
            "level": int(s.level),
            "name": s.name,
            "message": s.message,
            "hardware_id": s.hardware_id,
            "values": [{"key": k, "value": v} for k, v in s.values],
        }
        for s in statuses
    ]


def read_frames(
    path: Path, say: Callable[[str], None]
) -> Generator[can.Message, None, tuple[int, int]]:
    """The raw frames of an MCAP recording, in order, up to where it breaks off: read as a
    stream from the start, it needs no summary (a ``kill -9`` or a full disk leaves none)."""
    try:
        from mcap.exceptions import EndOfFile
        from mcap.records import Channel, Message
        from mcap.stream_reader import StreamReader
    except ImportError as exc:
        raise BusOpenError(f"{path}: reading .mcap needs the mcap library: {INSTALL_HINT}") from exc
    read = 0
    channels: dict[int, str] = {}
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    topic = channels.get(rec.channel_id, "")
                    if topic.startswith("/can/"):
                        read += 1
                        yield _frame(rec.data, topic)
        except EndOfFile:  # no summary and footer: the recording did not end normally
            say(
                f"{path}: the file breaks off after frame {read}, without the summary a finished"
                " recording has (killed, or the disk filled): read up to there"
            )
            return read, 1
        except Exception as exc:  # damaged
            say(f"{path}: cannot read past frame {read} ({str(exc) or type(exc).__name__})")
            return read, 1
    return read, 0


def _frame(cdr: bytes, topic: str) -> can.Message:
    """can_msgs/Frame from its CDR bytes: the header's string sets where the rest starts."""
    import struct

    sec, nanosec, length = struct.unpack_from("<iII", cdr, 4)
    at = 4 + 12 + length
    at += -(at - 4) % 4  # uint32 id aligned to 4 from the start of the data
    ident, rtr, extended, error, dlc = struct.unpack_from("<I???B", cdr, at)
    data = cdr[at + 8 : at + 16]
    return can.Message(
        timestamp=sec + nanosec / 1e9,
        arbitration_id=ident,
        is_extended_id=extended,
        is_remote_frame=rtr,
        is_error_frame=error,
        is_rx=topic.endswith("/rx"),
        dlc=dlc,
        data=data[:dlc],
        channel=topic.split("/")[2],
    )
