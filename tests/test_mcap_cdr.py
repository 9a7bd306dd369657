"""The struct-made CDR encoders (runtime/cdr.py, used by runtime/ros_topics.py) write, for
every message we record, the very bytes mcap_ros2's ``serialize_dynamic`` writes — edge
values included — and a recording made with them reads back with the same values through
the mcap reader with mcap_ros2's decoder and through rosbags."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from abh3_supervisor.config import parse_config
from abh3_supervisor.protocol import frames
from abh3_supervisor.runtime import cdr
from abh3_supervisor.runtime.mcap_recording import McapRecording
from abh3_supervisor.runtime.ros_topics import SCHEMAS, VENDOR, RosTopics
from abh3_supervisor.scheduler.core import StatusEvent
from tests.support.rig import Rig

pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from mcap_ros2.decoder import DecoderFactory

from tests.support.rig import set_twist

INT32 = (-(2**31), -1, 0, 1, 2**31 - 1)
FLOATS = (0.0, -0.0, 1.5, -273.15, 1e308, -1e308, 5e-324, math.inf, -math.inf, math.nan)
NAMES = ("", "b", "ab", "abc", "abcd", "démo", "日本語のバス", "x" * 37)  # every alignment


def reference(schema: str, message: dict[str, Any]) -> bytes:
    return bytes(serialize_dynamic(schema, SCHEMAS[schema])[schema](message))


def stamp(sec: int, nanosec: int, frame_id: str) -> dict[str, Any]:
    return {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id}


# ------------------------------------------------------------ byte for byte


@pytest.mark.parametrize("bus", NAMES)
@pytest.mark.parametrize("length", range(9))
def test_a_frame_is_the_bytes_serialize_dynamic_writes(bus: str, length: int) -> None:
    data = bytes(range(0xF8, 0xF8 + length))
    for sec, nanosec, ident, flags in [
        (0, 0, 0, (False, False, False)),
        (-(2**31), 999_999_999, 0x1FFFFFFF, (True, True, True)),
        (2**31 - 1, 1, 0x7FF, (False, True, False)),
    ]:
        ours = cdr.frame_encoder(bus)(sec, nanosec, ident, *flags, length, bytearray(data))
        assert ours == reference(
            "can_msgs/msg/Frame",
            {
                "header": stamp(sec, nanosec, bus),
                "id": ident,
                "is_rtr": flags[0],
                "is_extended": flags[1],
                "is_error": flags[2],
                "dlc": length,
                "data": list(data + bytes(8 - length)),
            },
        )


def test_a_frame_longer_than_8_bytes_keeps_its_first_8_as_before() -> None:
    ours = cdr.frame_encoder("fd")(1, 2, 3, False, True, False, 12, bytes(range(12)))
    assert ours[-8:] == bytes(range(8))


@pytest.mark.parametrize("name", VENDOR)
def test_every_vendor_message_is_the_bytes_serialize_dynamic_writes(name: str) -> None:
    types = VENDOR[name].split()[0::2]
    fields = VENDOR[name].split()[1::2]
    pools = [INT32 if t == "int32" else FLOATS for t in types]
    for i in range(max(len(p) for p in pools)):
        values = [pool[(i + k) % len(pool)] for k, pool in enumerate(pools)]
        schema = f"abh3_can_interface/msg/{name}"
        assert cdr.flat_encoder(VENDOR[name])(*values) == reference(
            schema, dict(zip(fields, values, strict=True))
        ), values


@pytest.mark.parametrize("frame_id", NAMES)
@pytest.mark.parametrize("child", ["", "base_link", "ロボット"])
def test_odometry_is_the_bytes_serialize_dynamic_writes(frame_id: str, child: str) -> None:
    for v in (FLOATS, FLOATS[::-1]):
        x, y, qx, qy, qz, qw, lin, ang = (v * 2)[:8]
        ours = cdr.odometry_encoder(frame_id, child)(-7, 5, x, y, qx, qy, qz, qw, lin, ang)
        zero36 = [0.0] * 36
        message = {
            "header": stamp(-7, 5, frame_id),
            "child_frame_id": child,
            "pose": {
                "pose": {
                    "position": {"x": x, "y": y, "z": 0.0},
                    "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
                },
                "covariance": zero36,
            },
            "twist": {
                "twist": {
                    "linear": {"x": lin, "y": 0.0, "z": 0.0},
                    "angular": {"x": 0.0, "y": 0.0, "z": ang},
                },
                "covariance": zero36,
            },
        }
        assert ours == reference("nav_msgs/msg/Odometry", message)


def test_odometry_with_its_covariances_is_the_bytes_serialize_dynamic_writes() -> None:
    pose_cov = [float(i) / 7 for i in range(36)]
    twist_cov = [float(-i) * 1e-3 for i in range(36)]
    ours = cdr.odometry_encoder("odom", "base_link")(
        3, 9, 1.5, -2.0, 0.0, 0.0, 0.1, 0.99, 0.4, -0.2, pose_cov, twist_cov
    )
    message = {
        "header": stamp(3, 9, "odom"),
        "child_frame_id": "base_link",
        "pose": {
            "pose": {
                "position": {"x": 1.5, "y": -2.0, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.1, "w": 0.99},
            },
            "covariance": pose_cov,
        },
        "twist": {
            "twist": {
                "linear": {"x": 0.4, "y": 0.0, "z": 0.0},
                "angular": {"x": 0.0, "y": 0.0, "z": -0.2},
            },
            "covariance": twist_cov,
        },
    }
    assert ours == reference("nav_msgs/msg/Odometry", message)


def diagnostics_reference(sec: int, nanosec: int, frame_id: str, statuses: Any) -> bytes:
    return reference(
        "diagnostic_msgs/msg/DiagnosticArray",
        {
            "header": stamp(sec, nanosec, frame_id),
            "status": [
                {
                    "level": level,
                    "name": name,
                    "message": message,
                    "hardware_id": hw,
                    "values": [{"key": k, "value": v} for k, v in values],
                }
                for level, name, message, hw, values in statuses
            ],
        },
    )


def test_diagnostics_none_one_and_many_are_the_bytes_serialize_dynamic_writes() -> None:
    many = [
        (
            i % 4,
            f"abh3_supervisor: unit u{i}" + "é" * (i % 3),
            NAMES[i % len(NAMES)],
            "" if i % 2 else f"id{i}",
            tuple((f"k{j}" * (j % 3), NAMES[(i + j) % len(NAMES)]) for j in range(i % 6)),
        )
        for i in range(120)
    ]
    for statuses in ([], many[:1], many):
        for frame_id in ("", "abc", "診断"):
            ours = cdr.diagnostic_array(1_700_000_000, 123, frame_id, statuses)
            assert ours == diagnostics_reference(1_700_000_000, 123, frame_id, statuses)


text = st.text(max_size=12)
status = st.tuples(
    st.integers(0, 255), text, text, text, st.lists(st.tuples(text, text), max_size=4)
)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(-(2**31), 2**31 - 1),
    st.integers(0, 2**32 - 1),
    text,
    st.lists(status, max_size=6),
)
def test_any_diagnostics_are_the_bytes_serialize_dynamic_writes(
    sec: int, nanosec: int, frame_id: str, statuses: list[Any]
) -> None:
    ours = cdr.diagnostic_array(sec, nanosec, frame_id, statuses)
    assert ours == diagnostics_reference(sec, nanosec, frame_id, statuses)


@settings(max_examples=200, deadline=None)
@given(
    text,
    st.integers(0, 2**32 - 1),
    st.booleans(),
    st.booleans(),
    st.booleans(),
    st.binary(max_size=8),
)
def test_any_frame_is_the_bytes_serialize_dynamic_writes(
    bus: str, ident: int, rtr: bool, ext: bool, err: bool, data: bytes
) -> None:
    ours = cdr.frame_encoder(bus)(12, 34, ident, rtr, ext, err, len(data), data)
    message = {
        "header": stamp(12, 34, bus),
        "id": ident,
        "is_rtr": rtr,
        "is_extended": ext,
        "is_error": err,
        "dlc": len(data),
        "data": list(data.ljust(8, b"\0")),
    }
    assert ours == reference("can_msgs/msg/Frame", message)


# ------------------------------------------------------------ what a run produces

ROBOT = """
buses: {b: {interface: virtual, channel: cdr-test, simulate: true}}
units:
  - {name: l, abh3_id: 1, broadcast: {mask: 0x7f, rate_hz: 50}}
  - {name: r, abh3_id: 3, protocol: "2023", broadcast: {mask: 0x7f, rate_hz: 20}}
robots:
  - name: rover
    track_m: 0.5
    diameter_m: 0.2
    gear_ratio: 10
    pulses_per_rev: 4096
    frame_id: world
    child_frame_id: rover_base
    wheels:
      - {unit: l, axis: A, side: left}
      - {unit: r, axis: A, side: right, sign: -1}
"""


class Collect:
    def __init__(self) -> None:
        self.messages: list[tuple[str, str, bytes, int]] = []

    def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        self.messages.append((topic, schema, data, ns))


def test_every_message_of_a_run_re_encodes_to_its_own_bytes() -> None:
    """A simulated robot moving: every message decoded by mcap_ros2 and encoded again by
    it gives back our bytes (a wrong alignment or padding byte would not), and every
    schema is met."""
    config = parse_config(ROBOT, "robot.yaml")
    rig = Rig(config)
    sink = Collect()
    topics = RosTopics(config, [sink])
    topics.attach(rig.sup, rig.timeline.clock)
    rig.sup.subscribe(topics.observe)
    for unit in config.units:
        for command in ("SERVO ON ON", "START ON ON"):
            rig.sup.apply_text(unit, command)
    owner = rig.own("l")
    set_twist(rig.sup, "rover", 0.3, -0.4, source=owner)
    rig.run(1.5)
    assert {schema for _, schema, _, _ in sink.messages} == set(SCHEMAS) - {"can_msgs/msg/Frame"}
    decoders: dict[str, Any] = {}
    for topic, schema, data, _ in sink.messages:
        if schema not in decoders:
            decoders[schema] = generate_dynamic(schema, SCHEMAS[schema])[schema]
        assert reference(schema, decoders[schema](data)) == data, topic


def test_a_recording_reads_back_with_the_values_put_in(tmp_path: Path) -> None:
    """Edge values through the whole path — RosTopics, the .mcap sink, the file — read
    back by the mcap reader with mcap_ros2's decoder, and by rosbags."""
    config = parse_config(ROBOT.replace("cdr-test", "cdr-file"), "robot.yaml")
    rig = Rig(config)
    path = tmp_path / "edges.mcap"
    recording = McapRecording(path.open("wb"), config)
    recording.attach(rig.sup, rig.timeline.clock)
    sent = [
        can.Message(
            arbitration_id=0x1FFFFFFF - n,
            data=bytes(range(250, 250 + n)) if n < 6 else bytes([n] * n),
            channel="cdr-file",
            timestamp=1_700_000_000.25 + n,
            is_rx=bool(n % 2),
            is_remote_frame=n == 3,
        )
        for n in range(9)
    ]
    for msg in sent:
        recording.on_message_received(msg)
    records: list[frames.Broadcast] = [
        frames.Brd0(error=0xFFFFFFFF, alarm=0x80000000),
        frames.Brd1(io=0x7FFFFFFF, control=None, inputs=0x80000001),
        frames.Brd2(-6000.0, 6000.0, -0.5, 1e308),
        frames.Brd3(-300.0, 300.0, -0.0, 100.0, 0, 1000),
        frames.Brd4(pulse_a=-(2**31), pulse_b=2**31 - 1),
        frames.Brd5(-10.0, 10.0, 48.2, 24.0),
        frames.Brd6(-1e-300, 5e-324),
    ]
    for n, record in enumerate(records):
        recording.observe(StatusEvent("l", 0.5 + n / 10, n, record))
    recording.stop()
    expected: dict[int, dict[str, float]] = {
        0: {"error": -1, "alarm": -(2**31)},
        1: {"control": -(2**31) + 1, "in_out": 2**31 - 1},
        2: {"vel_cmd_ay": -6000.0, "vel_cmd_bx": 6000.0, "vel_fbk_ay": -0.5, "vel_fbk_bx": 1e308},
        3: {"cur_cmd_ay": -300.0, "cur_cmd_bx": 300.0, "load_a": -0.0, "load_b": 100.0},
        4: {"pulse_a": -(2**31), "pulse_b": 2**31 - 1},
        5: {"analog0": -10.0, "analog1": 10.0, "main_volt": 48.2, "control_volt": 24.0},
        6: {"monitor0": -1e-300, "monitor1": 5e-324},
    }

    def check(topic: str, msg: Any) -> None:
        if topic.startswith("/can/"):
            original = sent[msg.header.stamp.sec - 1_700_000_000]
            assert topic == f"/can/b/{'rx' if original.is_rx else 'tx'}"
            assert msg.header.frame_id == "b"
            ns = int(original.timestamp * 1e9)  # as a .log has it, to the float's precision
            assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == divmod(ns, 10**9)
            assert msg.id == original.arbitration_id
            assert (msg.dlc, bytes(msg.data)) == (
                original.dlc,
                bytes(original.data).ljust(8, b"\0"),
            )
            assert msg.is_rtr == original.is_remote_frame and msg.is_extended
        elif topic == "/diagnostics":  # the first event's: the rig's health as it stands
            assert {s.name for s in msg.status} == {
                "abh3_supervisor: bus b", "abh3_supervisor: unit l", "abh3_supervisor: unit r",
                "abh3_supervisor: robot rover",  # the robot decision's status
            }  # fmt: skip
            assert all(kv.key for one in msg.status for kv in one.values)
        else:
            packet = int(topic.removeprefix("/l/brd").removesuffix("_data"))
            assert {k: getattr(msg, k) for k in expected[packet]} == expected[packet], topic

    seen = 0
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, decoded in reader.iter_decoded_messages():
            check(channel.topic, decoded)
            seen += 1
            assert message.sequence >= 1
    assert seen == len(sent) + len(records) + 1  # and one /diagnostics
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as bag:
        read = 0
        for connection, _, raw in bag.messages():
            check(connection.topic, bag.deserialize(raw, connection.msgtype))
            read += 1
    assert read == seen


class Fails:
    def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        raise OSError(28, "No space left on device")


def test_a_failing_sink_is_dropped_once_and_the_others_get_every_message(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = parse_config(ROBOT, "robot.yaml")
    before, after = Collect(), Collect()
    failing = Fails()
    topics = RosTopics(config, [before, failing, after])
    with caplog.at_level(logging.WARNING):
        for i in range(5):
            topics.on_message_received(can.Message(arbitration_id=i, channel="cdr-test"))
    assert len(before.messages) == len(after.messages) == 5
    assert topics.sinks == [before, after]
    assert [s for s, _ in topics.failures] == [failing]
    assert caplog.text.count("Fails failed (") == 1


def test_messages_added_in_one_pack_make_the_file_add_message_makes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """runtime/mcap_messages.py against the mcap Writer's own add_message: the same
    messages (many topics, chunks closed by size and by flushes) give the same bytes."""
    from abh3_supervisor.runtime import mcap_messages, mcap_recording

    monkeypatch.setattr(mcap_recording, "CHUNK_BYTES", 3000)  # chunks closed by size too
    config = parse_config(ROBOT, "robot.yaml")

    adders: list[object] = []

    def record(path: Path) -> bytes:
        rec = mcap_recording.open_mcap(path, config)
        adders.append(getattr(rec._add, "__self__", None))
        for i in range(3000):
            rec.on_message_received(
                can.Message(
                    arbitration_id=i % 7,
                    data=bytes([i % 256] * (i % 9)),
                    channel="cdr-test" if i % 3 else "another",
                    timestamp=1_700_000_000 + (i * 7919 % 3000) / 1000,  # not in order
                    is_rx=bool(i % 2),
                )
            )
            if i % 500 == 0:
                rec.flush()
        rec.stop()
        return path.read_bytes()

    fast = record(tmp_path / "fast.mcap")
    monkeypatch.setattr(
        mcap_messages,
        "fast_add",
        lambda writer: lambda c, ns, data, seq: writer.add_message(c, ns, data, ns, seq),
    )
    slow = record(tmp_path / "slow.mcap")
    assert fast == slow
    assert isinstance(adders[0], mcap_messages._Messages) and adders[1] is None
    with (tmp_path / "fast.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 3000 and len(summary.chunk_indexes) > 10


def test_a_full_disk_breaks_the_file_once_and_the_other_sinks_go_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The file's failure is raised once, to the recorder, after the other sinks of its
    topics got the message; they go on getting the next ones."""
    from abh3_supervisor.runtime import mcap_recording
    from tests.support.disk import FillsUp

    monkeypatch.setattr(mcap_recording, "CHUNK_BYTES", 4096)  # chunks written as it goes
    config = parse_config(ROBOT, "robot.yaml")
    real = (tmp_path / "full.mcap").open("wb")
    recording = McapRecording(FillsUp(real, 20_000), config)  # type: ignore[arg-type]
    live = Collect()
    recording.topics.sinks.append(live)
    raised = []
    for i in range(3000):
        try:
            recording.on_message_received(
                can.Message(arbitration_id=i, data=bytes(8), channel="cdr-test", timestamp=i)
            )
        except OSError as exc:
            raised.append((i, exc))
    recording.stop()
    real.close()
    assert len(raised) == 1 and "No space left" in str(raised[0][1]) and raised[0][0] < 2000
    assert recording.broken and recording.topics.sinks == [recording, live]
    assert [m[3] for m in live.messages] == [i * 10**9 for i in range(3000)]
