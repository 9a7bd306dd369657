"""DDS types exactly as ROS 2 puts the vendor's messages on the wire.

ROS 2 maps ``pkg/msg/Type`` to the DDS type ``pkg::msg::dds_::Type_`` and topic
``rt/<name>``; services use ``rq/<name>Request`` and ``rr/<name>Reply`` with types
``pkg::srv::dds_::Type_Request_`` / ``Type_Response_``, each sample preceded by the
request header rmw_cyclonedds writes: the last 8 bytes of the client's GUID (carried
here as a little-endian uint64, the same 8 bytes on the wire) and a 64-bit sequence
number. Field names and types follow the vendor's published files (protocol doc §9),
including the reply field ``responce``.
"""

# no `from __future__ import annotations`: cyclonedds reads the field types at runtime
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Annotated

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float64, int32, int64, sequence, uint8, uint32, uint64


def _name(kind: str, typ: str, pkg: str = "abh3_can_interface") -> str:
    return f"{pkg}::{kind}::dds_::{typ}_"


@dataclass
class Abh3Velocity(IdlStruct, typename=_name("msg", "Abh3Velocity")):
    vel_ay: float64 = 0.0
    vel_bx: float64 = 0.0


@dataclass
class Abh3Current(IdlStruct, typename=_name("msg", "Abh3Current")):
    cur_ay: float64 = 0.0
    cur_bx: float64 = 0.0


@dataclass
class Abh3Input(IdlStruct, typename=_name("msg", "Abh3Input")):
    data: int32 = 0
    mask: int32 = 0


@dataclass
class Abh3Brd0(IdlStruct, typename=_name("msg", "Abh3Brd0")):
    error: int32 = 0
    alarm: int32 = 0


@dataclass
class Abh3Brd1(IdlStruct, typename=_name("msg", "Abh3Brd1")):
    control: int32 = 0
    in_out: int32 = 0


@dataclass
class Abh3Brd2(IdlStruct, typename=_name("msg", "Abh3Brd2")):
    vel_cmd_ay: float64 = 0.0
    vel_cmd_bx: float64 = 0.0
    vel_fbk_ay: float64 = 0.0
    vel_fbk_bx: float64 = 0.0


@dataclass
class Abh3Brd3(IdlStruct, typename=_name("msg", "Abh3Brd3")):
    cur_cmd_ay: float64 = 0.0
    cur_cmd_bx: float64 = 0.0
    load_a: float64 = 0.0
    load_b: float64 = 0.0


@dataclass
class Abh3Brd4(IdlStruct, typename=_name("msg", "Abh3Brd4")):
    pulse_a: int32 = 0
    pulse_b: int32 = 0


@dataclass
class Abh3Brd5(IdlStruct, typename=_name("msg", "Abh3Brd5")):
    analog0: float64 = 0.0
    analog1: float64 = 0.0
    main_volt: float64 = 0.0
    control_volt: float64 = 0.0


@dataclass
class Abh3Brd6(IdlStruct, typename=_name("msg", "Abh3Brd6")):
    monitor0: float64 = 0.0
    monitor1: float64 = 0.0


@dataclass
class Int32(IdlStruct, typename=_name("msg", "Int32", "std_msgs")):
    data: int32 = 0


@dataclass
class Vector3(IdlStruct, typename=_name("msg", "Vector3", "geometry_msgs")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Twist(IdlStruct, typename=_name("msg", "Twist", "geometry_msgs")):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class Time(IdlStruct, typename=_name("msg", "Time", "builtin_interfaces")):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename=_name("msg", "Header", "std_msgs")):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Point(IdlStruct, typename=_name("msg", "Point", "geometry_msgs")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename=_name("msg", "Quaternion", "geometry_msgs")):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename=_name("msg", "Pose", "geometry_msgs")):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


# float64[36], spelled so that type checkers read it too: array[float64, 36] is this
Covariance = Annotated[Sequence[float64], array(float64, 36)]


def _covariance() -> list[float]:
    return [0.0] * 36


@dataclass
class PoseWithCovariance(IdlStruct, typename=_name("msg", "PoseWithCovariance", "geometry_msgs")):
    pose: Pose = field(default_factory=Pose)
    covariance: Covariance = field(default_factory=_covariance)


@dataclass
class TwistWithCovariance(IdlStruct, typename=_name("msg", "TwistWithCovariance", "geometry_msgs")):
    twist: Twist = field(default_factory=Twist)
    covariance: Covariance = field(default_factory=_covariance)


@dataclass
class Odometry(IdlStruct, typename=_name("msg", "Odometry", "nav_msgs")):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)
    twist: TwistWithCovariance = field(default_factory=TwistWithCovariance)


@dataclass
class TwistStamped(IdlStruct, typename=_name("msg", "TwistStamped", "geometry_msgs")):
    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
class Transform(IdlStruct, typename=_name("msg", "Transform", "geometry_msgs")):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename=_name("msg", "TransformStamped", "geometry_msgs")):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename=_name("msg", "TFMessage", "tf2_msgs")):
    transforms: Annotated[Sequence[TransformStamped], sequence(TransformStamped)] = field(
        default_factory=list
    )


Floats = Annotated[Sequence[float64], sequence(float64)]


@dataclass
class JointState(IdlStruct, typename=_name("msg", "JointState", "sensor_msgs")):
    header: Header = field(default_factory=Header)
    name: Annotated[Sequence[str], sequence(str)] = field(default_factory=list)
    position: Floats = field(default_factory=list)
    velocity: Floats = field(default_factory=list)
    effort: Floats = field(default_factory=list)


def byte(value: int) -> int:
    """A ROS ``byte`` field's value: an octet, a plain int here (rclpy wants ``bytes``)."""
    return value


@dataclass
class KeyValue(IdlStruct, typename=_name("msg", "KeyValue", "diagnostic_msgs")):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename=_name("msg", "DiagnosticStatus", "diagnostic_msgs")):
    level: uint8 = 0  # ROS `byte`: an octet on the wire
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: Annotated[Sequence[KeyValue], sequence(KeyValue)] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename=_name("msg", "DiagnosticArray", "diagnostic_msgs")):
    header: Header = field(default_factory=Header)
    status: Annotated[Sequence[DiagnosticStatus], sequence(DiagnosticStatus)] = field(
        default_factory=list
    )


@dataclass
class Abh3InputRequest(IdlStruct, typename=_name("srv", "Abh3Input_Request")):
    """``inp_service`` request, with rmw_cyclonedds's request header in front."""

    client_guid: uint64 = 0  # the 8 GUID bytes, read little-endian
    sequence: int64 = 0
    command: str = ""


@dataclass
class Abh3InputResponse(IdlStruct, typename=_name("srv", "Abh3Input_Response")):
    """``inp_service`` reply: the header of the request it answers, then ``responce``."""

    client_guid: uint64 = 0  # the 8 GUID bytes, read little-endian
    sequence: int64 = 0
    responce: str = ""


BROADCASTS = (Abh3Brd0, Abh3Brd1, Abh3Brd2, Abh3Brd3, Abh3Brd4, Abh3Brd5, Abh3Brd6)
