"""``ros2``: the vendor sample's ROS 2 topics over DDS, with no ROS install needed.

This first part is read-only, so it is safe on any network: per unit, under the
namespace ``<namespace>/<unit>``, it publishes ``vel_fbk_ab`` and ``vel_fbk_yx`` after
every exchange (as ros2ABH3Cmd does), ``brd0_data`` … ``brd6_data`` for the unit's
broadcast mask on the scheduler's own polling, and serves the conversion node's topics
(``xa`` → ``xa_yx``, ``xa_ab``; ``yx`` → ``yx_xa``, ``yx_ab``; ``ab`` → ``ab_yx``,
``ab_xa``) with the unit's geometry. Commands (``vel_cmd``, ``cur_cmd``, ``inp_data``,
``inp_service``, ``cmd_vel``) come in a later step, behind ``allow_commands``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from cyclonedds.core import Listener, Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from abh3_plugins.ros2 import types
from abh3_supervisor import kinematics
from abh3_supervisor.config.source import Section
from abh3_supervisor.hookspecs import hookimpl
from abh3_supervisor.kinematics import Geometry
from abh3_supervisor.protocol import frames
from abh3_supervisor.state import Feedback
from abh3_supervisor.supervisor import Supervisor

log = logging.getLogger(__name__)
# ROS 2's default QoS for topics: reliable, keep the last 10, volatile
ROS_DEFAULT = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10))


def twist(linear_x: float, angular_z: float) -> types.Twist:
    return types.Twist(types.Vector3(linear_x, 0.0, 0.0), types.Vector3(0.0, 0.0, angular_z))


def _int32(value: int) -> int:
    """Flag words go out as the vendor's int32 fields: the same 32 bits, signed."""
    return value - (1 << 32) if value & 0x80000000 else value


def brd_message(record: frames.Broadcast) -> Any:
    if isinstance(record, frames.Brd0):
        return types.Abh3Brd0(_int32(record.error), _int32(record.alarm))
    if isinstance(record, frames.Brd1):
        # 2021: control + I/O; 2023 sends the input word where control was
        first = record.control if record.control is not None else record.inputs or 0
        return types.Abh3Brd1(_int32(first), _int32(record.io))
    if isinstance(record, frames.Brd2):
        return types.Abh3Brd2(
            record.vel_cmd_ay, record.vel_cmd_bx, record.vel_fbk_ay, record.vel_fbk_bx
        )
    if isinstance(record, frames.Brd3):
        return types.Abh3Brd3(record.cur_cmd_ay, record.cur_cmd_bx, record.load_a, record.load_b)
    if isinstance(record, frames.Brd4):
        return types.Abh3Brd4(record.pulse_a, record.pulse_b)
    if isinstance(record, frames.Brd5):
        return types.Abh3Brd5(record.analog0, record.analog1, record.main_volt, record.control_volt)
    if isinstance(record, frames.Brd6):
        return types.Abh3Brd6(record.monitor0, record.monitor1)
    return None  # broadcast 7 is not defined: nothing to publish


class _Converter:
    """The conversion node for one unit: three inputs, two outputs each."""

    def __init__(self, bridge: Ros2Plugin, ns: str, geometry: Geometry) -> None:
        g = geometry
        out = {
            name: bridge.writer(f"{ns}/{name}", typ)
            for name, typ in (
                ("xa_yx", types.Abh3Velocity),
                ("xa_ab", types.Abh3Velocity),
                ("yx_xa", types.Twist),
                ("yx_ab", types.Abh3Velocity),
                ("ab_yx", types.Abh3Velocity),
                ("ab_xa", types.Twist),
            )
        }

        def from_xa(m: types.Twist) -> None:
            y, x = kinematics.twist_to_yx(m.linear.x, m.angular.z, g)
            out["xa_yx"].write(types.Abh3Velocity(y, x))
            out["xa_ab"].write(types.Abh3Velocity(*kinematics.yx_to_ab(y, x)))

        def from_yx(m: types.Abh3Velocity) -> None:
            out["yx_xa"].write(twist(*kinematics.yx_to_twist(m.vel_ay, m.vel_bx, g)))
            out["yx_ab"].write(types.Abh3Velocity(*kinematics.yx_to_ab(m.vel_ay, m.vel_bx)))

        def from_ab(m: types.Abh3Velocity) -> None:
            out["ab_yx"].write(types.Abh3Velocity(*kinematics.ab_to_yx(m.vel_ay, m.vel_bx)))
            out["ab_xa"].write(twist(*kinematics.ab_to_twist(m.vel_ay, m.vel_bx, g)))

        bridge.reader(f"{ns}/xa", types.Twist, from_xa)
        bridge.reader(f"{ns}/yx", types.Abh3Velocity, from_yx)
        bridge.reader(f"{ns}/ab", types.Abh3Velocity, from_ab)


class Ros2Plugin:
    def __init__(self) -> None:
        self.domain_id = 0
        self.namespace = ""
        self.conversion = True
        self.participant: DomainParticipant | None = None
        self.readers: list[DataReader[Any]] = []
        self.fbk: dict[str, tuple[DataWriter[Any], DataWriter[Any]]] = {}
        self.brd: dict[tuple[str, int], DataWriter[Any]] = {}

    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        section.only({"domain_id", "namespace", "conversion", "allow_commands"})
        self.domain_id = section.integer("domain_id", 0, 0, 232)
        self.namespace = section.text("namespace", "/").rstrip("/")
        self.conversion = section.boolean("conversion", True)
        if section.boolean("allow_commands", False):
            section.error(
                "allow_commands",
                "commands over ROS 2 are not implemented yet: "
                "this version of the bridge only publishes",
            )

    def writer(self, name: str, typ: type) -> DataWriter[Any]:
        assert self.participant is not None
        return DataWriter(
            self.participant, Topic(self.participant, f"rt{name}", typ), qos=ROS_DEFAULT
        )

    def reader(self, name: str, typ: type, handle: Callable[[Any], None]) -> None:
        assert self.participant is not None

        def on_data(reader: DataReader[Any]) -> None:
            for sample in reader.take(N=64):
                if all(math.isfinite(v) for v in _numbers(sample)):
                    handle(sample)
                else:
                    log.warning("ros2: %s: non-finite value ignored", name)

        self.readers.append(
            DataReader(
                self.participant,
                Topic(self.participant, f"rt{name}", typ),
                qos=ROS_DEFAULT,
                listener=Listener(on_data_available=on_data),  # type: ignore[no-untyped-call]
            )
        )

    @hookimpl
    def abh3_start(self, supervisor: Supervisor) -> None:
        self.participant = DomainParticipant(self.domain_id)
        for name, unit in supervisor.units.items():
            ns = f"{self.namespace}/{name}"
            self.fbk[name] = (
                self.writer(f"{ns}/vel_fbk_ab", types.Abh3Velocity),
                self.writer(f"{ns}/vel_fbk_yx", types.Abh3Velocity),
            )
            for n in unit.cfg.broadcast.packets:  # only the mask's publishers, as the seed
                self.brd[(name, n)] = self.writer(f"{ns}/brd{n}_data", types.BROADCASTS[n])
            if self.conversion:
                _Converter(self, ns, unit.cfg.geometry)
        log.info(
            "ros2: publishing for %d unit(s) on DDS domain %d",
            len(supervisor.units),
            self.domain_id,
        )

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback) -> None:
        ab, yx = self.fbk[unit]
        ab.write(types.Abh3Velocity(feedback.vel_a, feedback.vel_b))
        yx.write(types.Abh3Velocity(feedback.vel_y, feedback.vel_x))

    @hookimpl
    def abh3_status(self, unit: str, packet: int, record: frames.Broadcast) -> None:
        writer = self.brd.get((unit, packet))
        message = brd_message(record)
        if writer is not None and message is not None:
            writer.write(message)

    @hookimpl
    def abh3_stop(self) -> None:
        self.readers.clear()
        self.participant = None  # cyclonedds deletes the entities with the participant


def _numbers(sample: Any) -> list[float]:
    if isinstance(sample, types.Twist):
        return [
            sample.linear.x,
            sample.linear.y,
            sample.linear.z,
            sample.angular.x,
            sample.angular.y,
            sample.angular.z,
        ]
    return [getattr(sample, f) for f in ("vel_ay", "vel_bx")]
