"""The DDS types of the ROS 2 interface, byte for byte against rosbags' CDR serializer
built from the ``.msg``/``.srv`` files we ship (an independent implementation)."""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path
from typing import Any

import pytest

cyclonedds = pytest.importorskip("cyclonedds")
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from abh3_plugins.ros2 import types  # noqa: E402

INTERFACE = (
    Path(__file__).resolve().parent.parent
    / "plugins"
    / "abh3_plugins"
    / "ros2"
    / "interface"
    / "abh3_can_interface"
)
MESSAGES: dict[str, tuple[Any, dict[str, Any]]] = {
    "Abh3Velocity": (types.Abh3Velocity, {"vel_ay": 300.2, "vel_bx": -20.4}),
    "Abh3Current": (types.Abh3Current, {"cur_ay": 12.5, "cur_bx": -3.0}),
    "Abh3Input": (types.Abh3Input, {"data": 0x1001, "mask": -0x7FFFFFFF}),
    "Abh3Brd0": (types.Abh3Brd0, {"error": 0x00400000, "alarm": 0x00400000}),
    "Abh3Brd1": (types.Abh3Brd1, {"control": 0x08070070, "in_out": 0xC3}),
    "Abh3Brd2": (
        types.Abh3Brd2,
        {"vel_cmd_ay": 0.0, "vel_cmd_bx": 1.0, "vel_fbk_ay": -2.6, "vel_fbk_bx": 0.2},
    ),
    "Abh3Brd3": (
        types.Abh3Brd3,
        {"cur_cmd_ay": 1.0, "cur_cmd_bx": 2.0, "load_a": 6.0, "load_b": 0.0},
    ),
    "Abh3Brd4": (types.Abh3Brd4, {"pulse_a": 141803, "pulse_b": 430787}),
    "Abh3Brd5": (
        types.Abh3Brd5,
        {"analog0": 0.21, "analog1": 0.14, "main_volt": 23.7, "control_volt": 23.7},
    ),
    "Abh3Brd6": (types.Abh3Brd6, {"monitor0": 0.011930, "monitor1": 0.106096}),
}


def store() -> Any:
    ts = get_typestore(Stores.EMPTY)
    for name in MESSAGES:
        text = (INTERFACE / "msg" / f"{name}.msg").read_text()
        ts.register(get_types_from_msg(text, f"abh3_can_interface/msg/{name}"))
    return ts


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_message_bytes_match_an_independent_cdr_implementation(name: str) -> None:
    cls, values = MESSAGES[name]
    ts = store()
    ros_type = f"abh3_can_interface/msg/{name}"
    expected = ts.serialize_cdr(ts.types[ros_type](**values), ros_type)
    assert cls(**values).serialize() == bytes(expected)
    assert cls.deserialize(bytes(expected)) == cls(**values)
    assert cls.__idl_typename__ == f"abh3_can_interface::msg::dds_::{name}_"


def test_shipped_definitions_have_the_vendors_field_names() -> None:
    for name, (cls, _) in MESSAGES.items():
        text = (INTERFACE / "msg" / f"{name}.msg").read_text()
        assert [line.split()[1] for line in text.splitlines()] == [
            f.name for f in dataclasses.fields(cls)
        ]
    srv = (INTERFACE / "srv" / "Abh3Input.srv").read_text()
    assert srv == "string command\n---\nstring responce\n"  # sic, as the vendor publishes


def test_service_samples_carry_the_rmw_cyclonedds_request_header() -> None:
    ts = get_typestore(Stores.EMPTY)
    ts.register(get_types_from_msg("string command", "abh3_can_interface/msg/Abh3InputRequestBody"))
    body = bytes(
        ts.serialize_cdr(
            ts.types["abh3_can_interface/msg/Abh3InputRequestBody"](command="SERVO ON ON"),
            "abh3_can_interface/msg/Abh3InputRequestBody",
        )
    )
    guid = int.from_bytes(bytes(range(1, 9)), "little")
    request = types.Abh3InputRequest(guid, 7, "SERVO ON ON")
    data = request.serialize()
    # encapsulation header, 8 GUID bytes, int64 sequence, then the message as ROS would send it
    assert data[:4] == body[:4]
    assert data[4:12] == bytes(range(1, 9)) and struct.unpack("<q", data[12:20]) == (7,)
    assert data[20:] == body[4:]
    assert (
        types.Abh3InputResponse.deserialize(
            types.Abh3InputResponse(guid, 7, "Invalid Command.").serialize()
        ).responce
        == "Invalid Command."
    )


def test_odometry_matches_rosbags_stock_nav_msgs() -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    t = ts.types
    covariance = [float(i) for i in range(36)]
    ours = types.Odometry(
        types.Header(types.Time(12, 345), "odom"),
        "base_link",
        types.PoseWithCovariance(
            types.Pose(types.Point(1.0, 2.0, 0.0), types.Quaternion(0.0, 0.0, 0.38, 0.92)),
            covariance,
        ),
        types.TwistWithCovariance(
            types.Twist(types.Vector3(0.5), types.Vector3(z=0.2)), covariance
        ),
    )
    np = pytest.importorskip("numpy")
    theirs = t["nav_msgs/msg/Odometry"](
        t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](12, 345), "odom"),
        "base_link",
        t["geometry_msgs/msg/PoseWithCovariance"](
            t["geometry_msgs/msg/Pose"](
                t["geometry_msgs/msg/Point"](1.0, 2.0, 0.0),
                t["geometry_msgs/msg/Quaternion"](0.0, 0.0, 0.38, 0.92),
            ),
            np.array(covariance),
        ),
        t["geometry_msgs/msg/TwistWithCovariance"](
            t["geometry_msgs/msg/Twist"](
                t["geometry_msgs/msg/Vector3"](0.5, 0.0, 0.0),
                t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.2),
            ),
            np.array(covariance),
        ),
    )
    assert ours.serialize() == bytes(ts.serialize_cdr(theirs, "nav_msgs/msg/Odometry"))
    assert types.Odometry.__idl_typename__ == "nav_msgs::msg::dds_::Odometry_"
    for cls, ros in ((types.Int32, "std_msgs/msg/Int32"), (types.Twist, "geometry_msgs/msg/Twist")):
        assert cls().serialize() == bytes(ts.serialize_cdr(t[ros](*_zeros(t, ros)), ros))


def _zeros(t: Any, ros: str) -> list[Any]:
    """Default field values for a rosbags type (all our defaults are zero)."""
    if ros == "std_msgs/msg/Int32":
        return [0]
    vector = t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0)
    return [vector, vector]


def test_tf_joint_state_and_twist_stamped_match_rosbags_stock_messages() -> None:
    """/tf (tf2_msgs/TFMessage), joint_states and joint_commands (sensor_msgs/JointState)
    and a stamped cmd_vel (geometry_msgs/TwistStamped), byte for byte (issue 51)."""
    np = pytest.importorskip("numpy")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    t = ts.types
    header = types.Header(types.Time(12, 345), "odom")
    theirs_header = t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](12, 345), "odom")
    vector, quaternion = t["geometry_msgs/msg/Vector3"], t["geometry_msgs/msg/Quaternion"]
    tf = types.TFMessage(
        [
            types.TransformStamped(
                header,
                "base_link",
                types.Transform(types.Vector3(1.0, 2.0), types.Quaternion(0.0, 0.0, 0.38, 0.92)),
            )
        ]
    )
    theirs_tf = t["tf2_msgs/msg/TFMessage"](
        [
            t["geometry_msgs/msg/TransformStamped"](
                theirs_header,
                "base_link",
                t["geometry_msgs/msg/Transform"](
                    vector(1.0, 2.0, 0.0), quaternion(0.0, 0.0, 0.38, 0.92)
                ),
            )
        ]
    )
    assert tf.serialize() == bytes(ts.serialize_cdr(theirs_tf, "tf2_msgs/msg/TFMessage"))
    joints = types.JointState(header, ["l", "r_joint"], [1.5, -2.25], [0.5, 0.25], [])
    theirs_joints = t["sensor_msgs/msg/JointState"](
        theirs_header,
        ["l", "r_joint"],
        np.array([1.5, -2.25]),
        np.array([0.5, 0.25]),
        np.array([], dtype=float),
    )
    ros = "sensor_msgs/msg/JointState"
    assert joints.serialize() == bytes(ts.serialize_cdr(theirs_joints, ros))
    back = types.JointState.deserialize(bytes(ts.serialize_cdr(theirs_joints, ros)))
    assert (list(back.name), list(back.velocity)) == (["l", "r_joint"], [0.5, 0.25])
    stamped = types.TwistStamped(header, types.Twist(types.Vector3(0.5), types.Vector3(z=0.2)))
    theirs_stamped = t["geometry_msgs/msg/TwistStamped"](
        theirs_header,
        t["geometry_msgs/msg/Twist"](vector(0.5, 0.0, 0.0), vector(0.0, 0.0, 0.2)),
    )
    ros = "geometry_msgs/msg/TwistStamped"
    assert stamped.serialize() == bytes(ts.serialize_cdr(theirs_stamped, ros))
    assert types.TFMessage.__idl_typename__ == "tf2_msgs::msg::dds_::TFMessage_"
    assert types.JointState.__idl_typename__ == "sensor_msgs::msg::dds_::JointState_"
