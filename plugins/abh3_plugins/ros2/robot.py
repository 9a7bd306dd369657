"""A robot's ``cmd_vel`` and ``odom``: one pair per robot, under the robot's namespace.

A ``cmd_vel`` drives the whole robot: its twist goes through the input arbitration from a
source whose units are the robot's, so every drive of it gets its wheels' speeds in one
decision (core/robot_motion.py). It is refused before that if any wheel's motor speed would
be beyond what the frame can carry. ``odom`` is the robot's pose from every wheel's pulse
counts and its twist from every wheel's velocity feedback (core/odometry.py), published
each time the robot's units have all reported their counts anew.

A one-drive robot made from a unit's ``geometry`` is the unit's own pair, as before
robots existed: the unit's names (``/<unit>/cmd_vel``, ``/<unit>/odom``), the unit's input
source (shared with its ``vel_cmd``), the seed's conversion and ``odom_frame`` /
``base_frame``. A declared robot's pair carries its own source and its frame ids from the
``robots:`` section.
"""

from __future__ import annotations

import concurrent.futures
import time
from collections.abc import Callable, Mapping
from typing import Any

from abh3_plugins.ros2.settings import Settings
from abh3_plugins.ros2.transport import Transport
from abh3_plugins.ros2.values import Guard, twist, twist_values
from abh3_supervisor.plugin_api import (
    RESPONSE_INVALID,
    InputFeed,
    InputSource,
    Odometer,
    Pose,
    RobotConfig,
    UnitView,
    frames,
    kinematics,
    motor_speeds,
    yaw_quaternion,
)


class RobotTopics:
    """A robot's ``cmd_vel`` (``commands``) and ``odom`` (when its odometry is known).

    ``geometry`` given: the one-drive robot of that unit's geometry (the seed's
    conversion). ``feed`` is read at every message: None once the inputs stopped.
    """

    def __init__(
        self,
        robot: RobotConfig,
        t: Transport,
        settings: Settings,
        *,
        states: Mapping[str, UnitView],
        feed: Callable[[], InputFeed | None],
        commands: bool,
        frame_ids: tuple[str, str],
        geometry: kinematics.Geometry | None = None,
        guard: Guard | None = None,
    ) -> None:
        self.robot, self.t, self.settings = robot, t, settings
        self.states, self.feed, self.frame_ids = states, feed, frame_ids
        self.geometry = geometry
        self.guard = guard or Guard(f"robot {robot.name}")
        ready = robot.odometry_ready if geometry is None else geometry.pulses_per_rev > 0
        self.odometer = Odometer(robot, geometry) if ready else None
        if self.odometer is not None:
            self.odom = t.publisher(self.name_of("odom"), t.msg.Odometry)
        if commands:
            t.subscribe(self.name_of("cmd_vel"), t.msg.Twist, self.guard("cmd_vel", self.cmd_vel))
            t.serve(self.name_of("enable"), self.enable)

    def name_of(self, name: str) -> str:
        return self.settings.name(self.robot.name, name)

    # ------------------------------------------------------------ incoming

    def motor_speeds(self, linear_x: float, angular_z: float) -> list[float]:
        """Every axis's motor speed [min⁻¹] for a twist, as asked (no limit, no ramp)."""
        if self.geometry is not None:  # the seed's conversion, as before robots
            return list(kinematics.twist_to_ab(linear_x, angular_z, self.geometry))
        return [v for ab in motor_speeds(self.robot, linear_x, angular_z).values() for v in ab]

    def cmd_vel(self, m: Any) -> None:
        linear_x, angular_z = twist_values(m)  # finite, or refused; beyond limits: clamped
        feed = self.feed()  # None once the inputs stopped
        if feed is not None:
            feed.twist(linear_x, angular_z)

    def enable(self, command: str) -> concurrent.futures.Future[str]:
        """The robot's ``enable`` service: ``ON`` switches SERVO and START of every wheel axis
        of its drives on as one act, ``OFF`` off; answers ``''`` once every drive reports it
        (on), else why not, naming the drive (docs/safety.md, "The robot decision")."""
        feed = self.feed()
        on = {"ON": True, "1": True, "OFF": False, "0": False}.get(command.strip().upper())
        if feed is None or on is None:
            done: concurrent.futures.Future[str] = concurrent.futures.Future()
            done.set_result(RESPONSE_INVALID)
            return done
        return feed.enable(on)

    # ------------------------------------------------------------ outgoing

    def status(self, unit: str, record: frames.Broadcast, t: float | None = None) -> None:
        """A unit's status packet (received at ``t`` on the supervisor's clock): its pulse
        counts move the robot's odometry on."""
        if self.odometer is None or not isinstance(record, frames.Brd4):
            return
        pose = self.odometer.pulses(unit, record.pulse_a, record.pulse_b, t)
        if pose is not None:
            self.odom(self._odometry(pose))

    def _odometry(self, pose: Pose) -> Any:
        assert self.odometer is not None
        msg = self.t.msg
        # read across threads: each a whole, immutable record
        linear_x, angular_z = self.odometer.twist(
            {u: self.states[u].feedback for u in self.robot.units}
        )
        now = time.time_ns()
        qx, qy, qz, qw = yaw_quaternion(pose.yaw)
        frame_id, child_frame_id = self.frame_ids
        return msg.Odometry(
            header=msg.Header(
                stamp=msg.Time(sec=now // 1_000_000_000, nanosec=now % 1_000_000_000),
                frame_id=frame_id,
            ),
            child_frame_id=child_frame_id,
            pose=msg.PoseWithCovariance(
                pose=msg.Pose(
                    position=msg.Point(x=pose.x, y=pose.y),
                    orientation=msg.Quaternion(x=qx, y=qy, z=qz, w=qw),
                )
            ),
            twist=msg.TwistWithCovariance(twist=twist(msg, linear_x, angular_z)),
        )


class RobotBridge(InputSource):
    """A declared robot's ``cmd_vel`` and ``odom``; its ``cmd_vel`` is an input source of
    its own whose units are the robot's (``ros2:<robot>/cmd_vel``)."""

    def __init__(
        self, robot: RobotConfig, t: Transport, settings: Settings, states: Mapping[str, UnitView]
    ) -> None:
        super().__init__(
            source_name(robot.name), robot.units, settings.priority, settings.command_timeout
        )
        self.robot = robot
        self.feed: InputFeed | None = None
        self.topics = RobotTopics(
            robot,
            t,
            settings,
            states={u: states[u] for u in robot.units},
            feed=lambda: self.feed,
            commands=settings.allow_commands,  # a robot's units are all commanded
            frame_ids=(robot.frame_id, robot.child_frame_id),
        )

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None  # from now on every incoming command is dropped

    def status(self, unit: str, record: frames.Broadcast, t: float | None = None) -> None:
        self.topics.status(unit, record, t)


def source_name(robot: str) -> str:
    """A declared robot's ``cmd_vel`` source in the arbitration (a unit's is ``ros2:<unit>``,
    and a robot may be named after one of its units)."""
    return f"ros2:{robot}/cmd_vel"
