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
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int32, int64, uint64


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
