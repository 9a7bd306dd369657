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
import logging
import time
import weakref
from collections.abc import Callable, Mapping
from typing import Any

from abh3_plugins.ros2.settings import Settings, joint_name
from abh3_plugins.ros2.transport import Transport
from abh3_plugins.ros2.values import Guard, Refused, twist, twist_values, within
from abh3_supervisor.plugin_api import (
    RESPONSE_INVALID,
    Feedback,
    InputFeed,
    InputSource,
    Odometer,
    Pose,
    RobotConfig,
    Role,
    UnitView,
    frames,
    kinematics,
    motor_speeds,
    yaw_quaternion,
)

log = logging.getLogger("abh3_plugins.ros2.bridge")


_shared: weakref.WeakKeyDictionary[Any, dict[str, Any]] = weakref.WeakKeyDictionary()


def shared_publisher(t: Transport, name: str, typ: type) -> Any:
    """One publisher per name and transport (every robot's transform goes on ``/tf``)."""
    publishers = _shared.setdefault(t, {})
    if name not in publishers:
        publishers[name] = t.publisher(name, typ)
    return publishers[name]


class Pacer:
    """Which samples of the command rate go out at ``rate_hz``: on a fixed grid, a sample
    within half a command period of its slot taken (so 20 Hz from 50 Hz is 20 Hz)."""

    def __init__(self, rate_hz: float, command_hz: float) -> None:
        self.period = 0.0 if rate_hz >= command_hz else 1.0 / rate_hz
        self.slack = 0.5 / command_hz
        self.due: float | None = None

    def __call__(self, t: float) -> bool:
        if self.period == 0.0:
            return True
        if self.due is not None and t < self.due - self.slack:
            return False
        self.due = (
            t + self.period
            if self.due is None or t > self.due + self.period
            else (self.due + self.period)
        )
        return True


def stamp(msg: Any, ns: int) -> Any:
    return msg.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class RobotTopics:
    """A robot's ``cmd_vel`` and ``joint_commands`` (``commands``), and its ``odom``,
    ``/tf`` transform and ``joint_states``.

    Odometry comes at the command rate (at most ``odom_rate_hz``): every round of its
    drives' DP0 replies gives a sample (core/odometry.py), its pose from the pulse counts
    (broadcast 4) carried on by the feedback between their rounds, or from the feedback
    alone where there are none. A robot of monitor units (no DP0 replies) publishes at its
    rounds of pulse counts, as before. ``geometry`` given: the one-drive robot of that
    unit's geometry (the seed's conversion). ``feed`` is read at every message: None once
    the inputs stopped.
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
        own = self.own = settings.of(robot.name)
        msg = t.msg
        cfgs = [states[u].cfg for u in robot.units]
        # DP0 replies clock the odometry; a monitor unit has none: its pulse counts do
        self.live = all(c.role is Role.COMMAND for c in cfgs)
        counts = all(4 in c.broadcast.packets for c in cfgs)
        ready = geometry.pulses_per_rev > 0 if geometry is not None else True
        self.odometer = Odometer(robot, geometry, counts=counts) if ready else None
        self.command_hz = min(c.command_rate_hz for c in cfgs)
        self.pace = Pacer(own.odom_rate_hz or self.command_hz, self.command_hz)
        self.tf = None
        if self.odometer is not None:
            self.odom = t.publisher(self.name_of("odom"), msg.Odometry)
            if own.odom_tf:
                if hasattr(msg, "TFMessage"):
                    self.tf = shared_publisher(t, settings.tf_name(robot.name), msg.TFMessage)
                else:
                    log.warning("ros2: robot %s: tf2_msgs is not importable: no /tf", robot.name)
        self.joints = tuple(
            own.joints.get(w.name, joint_name(w.unit, w.name[-1])) for w in robot.wheels
        )
        joints = own.joint_states and self.live and self.odometer is not None
        if joints and not hasattr(msg, "JointState"):
            log.warning(
                "ros2: robot %s: sensor_msgs is not importable: no joint_states", robot.name
            )
            joints = False
        self.joint_states = (
            t.publisher(self.name_of("joint_states"), msg.JointState) if joints else None
        )
        if commands:
            if own.cmd_vel_stamped:
                handle, typ = self.cmd_vel_stamped, msg.TwistStamped
            else:
                handle, typ = self.cmd_vel, msg.Twist
            t.subscribe(self.name_of("cmd_vel"), typ, self.guard("cmd_vel", handle))
            t.serve(self.name_of("enable"), self.enable)
            if joints:
                t.subscribe(
                    self.name_of("joint_commands"),
                    msg.JointState,
                    self.guard("joint_commands", self.joint_commands),
                )

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

    def cmd_vel_stamped(self, m: Any) -> None:
        """A TwistStamped: older than ``command_timeout_ms`` (a zero stamp too) is stale,
        refused as silence would be."""
        age = time.time() - (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)
        if age > self.settings.command_timeout:
            raise Refused(
                f"stamped {age:.3f} s ago, more than command_timeout_ms "
                f"{self.settings.command_timeout * 1000:g}: stale"
            )
        self.cmd_vel(m.twist)

    def joint_commands(self, m: Any) -> None:
        """A JointState's velocities [rad/s] for the robot's wheel joints (others ignored):
        each side the mean of its wheels', as one twist through the same decision, limits,
        owner and timeout as ``cmd_vel``."""
        if len(m.velocity) != len(m.name):
            raise Refused(f"{len(m.name)} names but {len(m.velocity)} velocities")
        given = dict(zip(m.name, m.velocity, strict=True))
        missing = [j for j in self.joints if j not in given]
        if missing:
            raise Refused(f"no velocity for joint(s) {', '.join(missing)}")
        within(None, *(given[j] for j in self.joints))
        sides: dict[str, list[float]] = {"left": [], "right": []}
        for w, j in zip(self.robot.wheels, self.joints, strict=True):
            sides[w.side.value].append(given[j] * w.diameter_m / 2)
        left, right = (sum(v) / len(v) for v in (sides["left"], sides["right"]))
        feed = self.feed()
        if feed is not None:
            feed.twist((left + right) / 2, (right - left) / self.robot.track_m)

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
        counts move the robot's odometry on (a monitor robot's publish it)."""
        if self.odometer is None or not isinstance(record, frames.Brd4):
            return
        pose = self.odometer.pulses(unit, record.pulse_a, record.pulse_b, t)
        if pose is not None and not self.live:
            linear_x, angular_z = self.odometer.twist(
                {u: self.states[u].feedback for u in self.robot.units}
            )
            covariance = self.odometer.pose_covariance("pulses")
            self._publish(pose, linear_x, angular_z, covariance, None)

    def feedback(self, unit: str, feedback: Feedback) -> None:
        """A unit's DP0 feedback: a round of the robot's is a sample of its odometry."""
        if self.odometer is None or not self.live:
            return
        sample = self.odometer.feedback(unit, feedback)
        if sample is not None and self.pace(sample.t):
            self._publish(
                sample.pose,
                sample.linear_x,
                sample.angular_z,
                sample.pose_covariance,
                sample,
                sample.twist_covariance,
            )

    def _publish(
        self,
        pose: Pose,
        linear_x: float,
        angular_z: float,
        pose_covariance: list[float],
        sample: Any,  # core.odometry.Sample, or None
        twist_covariance: list[float] | None = None,
    ) -> None:
        msg = self.t.msg
        now = stamp(msg, time.time_ns())
        qx, qy, qz, qw = yaw_quaternion(pose.yaw)
        frame_id, child_frame_id = self.frame_ids
        orientation = msg.Quaternion(x=qx, y=qy, z=qz, w=qw)
        self.odom(
            msg.Odometry(
                header=msg.Header(stamp=now, frame_id=frame_id),
                child_frame_id=child_frame_id,
                pose=msg.PoseWithCovariance(
                    pose=msg.Pose(position=msg.Point(x=pose.x, y=pose.y), orientation=orientation),
                    covariance=pose_covariance,
                ),
                twist=msg.TwistWithCovariance(
                    twist=twist(msg, linear_x, angular_z),
                    covariance=twist_covariance or [0.0] * 36,
                ),
            )
        )
        if self.tf is not None:
            self.tf(
                msg.TFMessage(
                    transforms=[
                        msg.TransformStamped(
                            header=msg.Header(stamp=now, frame_id=frame_id),
                            child_frame_id=child_frame_id,
                            transform=msg.Transform(
                                translation=msg.Vector3(x=pose.x, y=pose.y), rotation=orientation
                            ),
                        )
                    ]
                )
            )
        if self.joint_states is not None and sample is not None:
            self.joint_states(
                msg.JointState(
                    header=msg.Header(stamp=now, frame_id=""),
                    name=list(self.joints),
                    position=list(sample.positions),
                    velocity=list(sample.velocities),
                    effort=[],
                )
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

    def feedback(self, unit: str, feedback: Feedback) -> None:
        self.topics.feedback(unit, feedback)


def source_name(robot: str) -> str:
    """A declared robot's ``cmd_vel`` source in the arbitration (a unit's is ``ros2:<unit>``,
    and a robot may be named after one of its units)."""
    return f"ros2:{robot}/cmd_vel"
