"""CDR encoders for the ROS 2 messages of :mod:`.ros_topics`, made once per message type
(and per constant frame id): a precompiled :class:`struct.Struct` each, so that encoding a
message on the bus loop is one ``pack`` call — no dicts, no per-field Python.

The bytes are exactly what rosbag2 and mcap_ros2's ``serialize_dynamic`` write (the tests
compare them byte for byte): the encapsulation header ``00 01 00 00`` (plain CDR,
little-endian), then the fields in order, each primitive aligned to its own size counted
from after the header; a string is its UTF-8 length + 1 (``uint32``), the bytes and a NUL;
a fixed array is its elements, a sequence a ``uint32`` count and its elements.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Sequence

HEADER = b"\x00\x01\x00\x00"  # CDR_LE, no options
_CODES = {"float64": ("d", 8), "int32": ("i", 4)}  # the vendor messages' field types


class Layout:
    """A ``struct`` format for a fixed CDR layout, its alignment padding worked out once.
    ``struct``'s ``<`` adds no padding of its own: each gap is written as ``x`` bytes."""

    def __init__(self) -> None:
        self.parts = ["<4s"]  # the header, not counted for alignment
        self.offset = 0

    def add(self, code: str, size: int, count: int = 1) -> Layout:
        """``count`` values of ``size`` bytes each (``struct`` code ``code``)."""
        self._align(size)
        self.parts.append(f"{count}{code}" if count > 1 else code)
        self.offset += size * count
        return self

    def zeros(self, size: int, count: int) -> Layout:
        """``count`` values that are always 0 (a covariance): padding, no argument."""
        self._align(size)
        self.parts.append(f"{size * count}x")
        self.offset += size * count
        return self

    def string(self, data: bytes) -> Layout:
        """A string whose bytes are known now: its length, then the bytes and the NUL
        (``s`` pads it); passed as two arguments, ``len(data) + 1`` and ``data``."""
        self.add("I", 4)
        self.parts.append(f"{len(data) + 1}s")
        self.offset += len(data) + 1
        return self

    def _align(self, size: int) -> None:
        pad = -self.offset % size
        if pad:
            self.parts.append(f"{pad}x")
            self.offset += pad

    def struct(self) -> struct.Struct:
        return struct.Struct("".join(self.parts))


FrameEncoder = Callable[[int, int, int, bool, bool, bool, int, bytes | bytearray], bytes]


def frame_encoder(frame_id: str) -> FrameEncoder:
    """``can_msgs/msg/Frame`` with ``header.frame_id`` = ``frame_id``: called with
    (sec, nanosec, id, is_rtr, is_extended, is_error, dlc, data); ``data`` is padded
    with zeros or cut to its 8 bytes."""
    fid = frame_id.encode()
    size = len(fid) + 1
    pack = (
        Layout().add("i", 4).add("I", 4).string(fid).add("I", 4)
        .add("?", 1).add("?", 1).add("?", 1).add("B", 1).add("s", 1, 8)
        .struct().pack
    )  # fmt: skip

    def encode(
        sec: int, nanosec: int, ident: int, rtr: bool, ext: bool, err: bool, dlc: int,
        data: bytes | bytearray,
    ) -> bytes:  # fmt: skip
        return pack(HEADER, sec, nanosec, size, fid, ident, rtr, ext, err, dlc, data)

    return encode


def flat_encoder(msgdef: str) -> Callable[..., bytes]:
    """A message of ``float64`` and ``int32`` fields only (the vendor's): called with its
    values in the order of the definition."""
    layout = Layout()
    for line in msgdef.splitlines():
        code, size = _CODES[line.split()[0]]
        layout.add(code, size)
    pack = layout.struct().pack

    def encode(*values: float) -> bytes:
        return pack(HEADER, *values)

    return encode


OdomEncoder = Callable[..., bytes]
ZERO_COVARIANCE = (0.0,) * 36


def odometry_encoder(frame_id: str, child_frame_id: str) -> OdomEncoder:
    """``nav_msgs/msg/Odometry`` of a robot on the ground, its frame ids fixed: called
    with (sec, nanosec, x, y, qx, qy, qz, qw, linear.x, angular.z) and, optionally, the
    pose's and the twist's covariance (36 values each; zero when not given);
    position.z and the other twist components are 0."""
    fid, cid = frame_id.encode(), child_frame_id.encode()
    fsize, csize = len(fid) + 1, len(cid) + 1
    pack = (
        Layout().add("i", 4).add("I", 4).string(fid).string(cid)
        .add("d", 8, 7).add("d", 8, 36)  # pose: position, orientation; covariance
        .add("d", 8, 6).add("d", 8, 36)  # twist: linear, angular; covariance
        .struct().pack
    )  # fmt: skip

    def encode(
        sec: int, nanosec: int, x: float, y: float, qx: float, qy: float, qz: float, qw: float,
        linear: float, angular: float, pose_covariance: Sequence[float] = ZERO_COVARIANCE,
        twist_covariance: Sequence[float] = ZERO_COVARIANCE,
    ) -> bytes:  # fmt: skip
        return pack(
            HEADER, sec, nanosec, fsize, fid, csize, cid,
            x, y, 0.0, qx, qy, qz, qw, *pose_covariance,
            linear, 0.0, 0.0, 0.0, 0.0, angular, *twist_covariance,
        )  # fmt: skip

    return encode


# one diagnostic status: (level, name, message, hardware_id, ((key, value), ...))
DiagStatus = tuple[int, str, str, str, Sequence[tuple[str, str]]]
_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")


def diagnostic_array(
    sec: int, nanosec: int, frame_id: str, statuses: Iterable[DiagStatus]
) -> bytes:
    """``diagnostic_msgs/msg/DiagnosticArray``: of varying length (once a second, not on
    the hot path), written field by field with the same alignment rules."""
    out = bytearray(HEADER)
    out += _STAMP.pack(sec, nanosec)
    _string(out, frame_id)
    listed = list(statuses)
    _u32(out, len(listed))  # aligned: a string ends on any byte
    for level, name, message, hardware_id, values in listed:
        out.append(level)  # byte: no alignment
        for text in (name, message, hardware_id):
            _string(out, text)
        _u32(out, len(values))
        for key, value in values:
            _string(out, key)
            _string(out, value)
    return bytes(out)


def _u32(out: bytearray, value: int) -> None:
    out += bytes(-(len(out) - 4) % 4)
    out += _U32.pack(value)


def _string(out: bytearray, text: str) -> None:
    data = text.encode()
    _u32(out, len(data) + 1)
    out += data
    out.append(0)
