"""Odometry for navigation (issue 51): ``/<robot>/odom`` at the command rate, ``/tf`` and
``joint_states`` with it, ``joint_commands`` and a stamped ``cmd_vel`` driving the robot —
the ROS 2 plugin on the fake clock with the simulated drives (tests/support/ros2_rig.py).

The AGV of docs/nav2.md: two drives, one wheel each, 0.2 m wheels, 20:1, 4096 pulses per
motor revolution, 0.45 m track. Its drives broadcast their pulse counts (packet 4) at a
third of 50 status polls a second, so the pose between two rounds of counts comes from
the integrated velocity feedback.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import pytest

pytest.importorskip("cyclonedds")
from abh3_plugins.ros2 import types
from abh3_plugins.ros2.robot import Pacer, RobotTopics
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.advice import odometry
from abh3_supervisor.core.odometry import POSE_VARIANCE
from abh3_supervisor.core.robot import Side
from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.core import FeedbackEvent, StatusEvent
from tests.support.robot_truth import Truth
from tests.support.ros2_rig import Bridged

AGV = """
buses: {{b: {{interface: virtual, channel: agv, simulate: true}}}}
units:
  - {{name: left_drive, abh3_id: 1, broadcast: {{mask: {mask}, rate_hz: 50}}}}
  - {{name: right_drive, abh3_id: 3, broadcast: {{mask: {mask}, rate_hz: 50}}}}
robots:
  - name: agv
    track_m: 0.45
    diameter_m: 0.2
    gear_ratio: 20
    pulses_per_rev: 4096
    wheels:
      - {{unit: left_drive, axis: A, side: left}}
      - {{unit: right_drive, axis: A, side: right, sign: -1}}
plugins:
  ros2: {{allow_commands: true, diagnostics_hz: 0, command_timeout_ms: 300{extra}}}
"""
TWIST = (0.3, 0.4)
STEP = 0.001


def agv(monkeypatch: pytest.MonkeyPatch, mask: str = "0x13", extra: str = "") -> Bridged:
    return Bridged(AGV.format(mask=mask, extra=extra), monkeypatch)


def source_of(odom: Any) -> str:
    """What the pose rests on, read back from its covariance."""
    x = odom.pose.covariance[0]
    return next(s for s, v in POSE_VARIANCE.items() if v[0] == x)


def drive(
    b: Bridged,
    seconds: float,
    command: Callable[[], None] | None,
    truth: Truth | None = None,
    each: Callable[[float], None] | None = None,
) -> None:
    """``seconds`` of fake time, ``command`` at 20 Hz (None: silence)."""
    for i in range(round(seconds / STEP)):
        if command is not None and i % 50 == 0:
            command()
        b.rig.run(STEP)
        if truth is not None:
            truth.step(STEP)
        if each is not None:
            each(b.rig.timeline.now)


def counting(b: Bridged) -> dict[str, int]:
    """Feedback rounds and pulse-count reports per unit, counted as they happen: the
    control the odometry's rate is compared with."""
    seen: dict[str, int] = {}

    def observe(event: object) -> None:
        if isinstance(event, FeedbackEvent):
            seen[f"fbk:{event.unit}"] = seen.get(f"fbk:{event.unit}", 0) + 1
        elif isinstance(event, StatusEvent) and isinstance(event.record, frames.Brd4):
            seen[f"brd4:{event.unit}"] = seen.get(f"brd4:{event.unit}", 0) + 1

    b.rig.sup.subscribe(observe)
    return seen


def twist_msg(linear: float, angular: float) -> Any:
    return types.Twist(types.Vector3(linear), types.Vector3(z=angular))


# ---------------------------------------------------------------- 1. odometry's rate


def test_odom_comes_at_the_command_rate_and_its_pose_follows_the_robot_between_counts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    b = agv(monkeypatch)
    robot = b.robot()
    drive(b, 0.5, None)
    odom = b.published("/agv/odom")
    odom.clear()
    seen = counting(b)
    truth = Truth(robot, b.motor)
    errors: list[float] = []

    def compare(now: float) -> None:
        if odom and getattr(odom[-1], "_checked", False) is False:
            p = odom[-1].pose.pose.position
            errors.append(math.hypot(p.x - truth.x, p.y - truth.y))
            object.__setattr__(odom[-1], "_checked", True)

    cmd_vel = b.t.handlers["/agv/cmd_vel"]
    drive(b, 2.0, lambda: cmd_vel(twist_msg(*TWIST)), truth, compare)
    rounds = min(seen["fbk:left_drive"], seen["fbk:right_drive"])
    pulses = min(seen["brd4:left_drive"], seen["brd4:right_drive"])
    # one odom per round of DP0 replies (both drives'): the command rate, 50 Hz
    assert abs(len(odom) - rounds) <= 1, (len(odom), rounds)
    assert len(odom) == pytest.approx(2.0 * 50, abs=2)
    assert pulses < len(odom) / 2  # the counts come at a third of that
    sources = [source_of(o) for o in odom]
    assert {"pulses", "integrated"} == set(sources)
    assert sources.count("pulses") == pytest.approx(pulses, abs=2)
    # between rounds of counts the pose moved on with the robot: never more than 5 mm
    # from where it really was (the truth: the simulated motors' speeds integrated)
    assert max(errors) < 0.005, max(errors)
    moving = odom[-1].twist.twist
    assert (moving.linear.x, moving.angular.z) == pytest.approx(TWIST, rel=0.01)
    assert odom[-1].twist.covariance[0] > 0


def test_odom_rate_hz_lowers_the_rate_and_tf_and_joint_states_come_with_odom(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    b = agv(monkeypatch, extra=", robots: {agv: {odom_rate_hz: 20}}")
    drive(b, 0.3, None)
    odom, tf, joints = (b.published(n) for n in ("/agv/odom", "/tf", "/agv/joint_states"))
    for topic in (odom, tf, joints):
        topic.clear()
    cmd_vel = b.t.handlers["/agv/cmd_vel"]
    drive(b, 2.0, lambda: cmd_vel(twist_msg(*TWIST)))
    assert len(odom) == pytest.approx(2.0 * 20, abs=1)
    assert len(tf) == len(joints) == len(odom)
    for o, t in zip(odom, tf, strict=True):
        (transform,) = t.transforms
        assert transform.header == o.header  # stamped as its odom, in its frames
        assert (transform.header.frame_id, transform.child_frame_id) == ("odom", "base_link")
        moved = transform.transform
        assert (moved.translation.x, moved.translation.y) == (
            o.pose.pose.position.x,
            o.pose.pose.position.y,
        )
        assert moved.rotation == o.pose.pose.orientation


def test_without_pulse_counts_the_pose_is_the_integrated_feedback_and_says_so(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    b = agv(monkeypatch, mask="0x03")  # no broadcast 4
    robot = b.robot()
    drive(b, 0.3, None)
    odom = b.published("/agv/odom")
    truth = Truth(robot, b.motor)
    cmd_vel = b.t.handlers["/agv/cmd_vel"]
    drive(b, 2.0, lambda: cmd_vel(twist_msg(*TWIST)), truth)
    drive(b, 0.5, None, truth)
    assert {source_of(o) for o in odom} == {"feedback"}
    last = odom[-1].pose.pose
    yaw = 2 * math.atan2(last.orientation.z, last.orientation.w)
    assert (last.position.x, last.position.y) == pytest.approx((truth.x, truth.y), abs=0.005)
    assert yaw == pytest.approx(truth.yaw, abs=0.01)


def test_the_pacer_keeps_the_asked_rate_on_the_command_rates_grid() -> None:
    for asked, command in ((20.0, 50.0), (10.0, 50.0), (25.0, 100.0), (50.0, 50.0)):
        pace = Pacer(asked, command)
        sent = sum(pace(i / command) for i in range(int(10 * command)))
        assert sent == pytest.approx(10 * asked, abs=1), (asked, command)


def test_check_says_each_robots_odometry_rate_and_source() -> None:
    on = parse_config(AGV.format(mask="0x13", extra=""), "agv.yaml")
    (line,) = odometry(on)
    assert line.startswith("robot agv: odom at 50 Hz (the command rate); pose from pulse counts")
    off = parse_config(AGV.format(mask="0x03", extra=", odom_rate_hz: 10"), "agv.yaml")
    (line,) = odometry(off)
    assert "odom at 10 Hz (odom_rate_hz; the command rate is 50 Hz)" in line
    assert "velocity feedback integrated (unit left_drive, right_drive without bit 4" in line


# ---------------------------------------------------------------- 2. tf


def test_tf_is_on_by_default_and_switched_off_per_robot(monkeypatch: pytest.MonkeyPatch) -> None:
    assert "/tf" in agv(monkeypatch).t.published
    off = agv(monkeypatch, extra=", robots: {agv: {odom_tf: false}}")
    assert "/tf" not in off.t.published and "/agv/odom" in off.t.published


# ---------------------------------------------------------------- 3. joints


def test_joint_states_are_the_wheels_angles_from_the_counts_and_speeds_from_feedback(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    b = agv(monkeypatch, extra=", robots: {agv: {joints: {left_drive.A: left_wheel_joint}}}")
    robot = b.robot()
    drive(b, 0.3, None)
    joints = b.published("/agv/joint_states")
    cmd_vel = b.t.handlers["/agv/cmd_vel"]
    drive(b, 1.5, lambda: cmd_vel(twist_msg(*TWIST)))
    last = joints[-1]
    assert list(last.name) == ["left_wheel_joint", "right_drive_a_wheel_joint"]
    # forward positive on both sides (the right motor is mirrored): v ∓ ω·track/2 over r
    side = {Side.LEFT: -1, Side.RIGHT: 1}
    expected = [(TWIST[0] + side[w.side] * TWIST[1] * 0.45 / 2) / 0.1 for w in robot.wheels]
    assert list(last.velocity) == pytest.approx(expected, rel=0.01)
    # the angle is the drive's own pulse count in wheel radians (mounting sign applied)
    for w, position in zip(robot.wheels, last.position, strict=True):
        count = b.rig.drive(w.unit).pulses[w.axis]
        rad = w.sign * count * 2 * math.pi / (4096 * 20)
        assert position == pytest.approx(rad, abs=abs(expected[0]) * 0.03 + 1e-3)


class RecordingFeed:
    def __init__(self) -> None:
        self.twists: list[tuple[float, float]] = []

    def twist(self, linear_x: float, angular_z: float) -> None:
        self.twists.append((linear_x, angular_z))


def joint_command(names: list[str], velocities: list[float]) -> Any:
    return types.JointState(name=names, velocity=velocities)


def test_joint_commands_are_the_same_twist_as_cmd_vel_through_the_same_feed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    b = agv(monkeypatch)
    topics: RobotTopics = b.plugin.robots["agv"].topics
    feed = RecordingFeed()
    topics.feed = lambda: feed  # type: ignore[assignment,return-value]
    left, right = (TWIST[0] - TWIST[1] * 0.225) / 0.1, (TWIST[0] + TWIST[1] * 0.225) / 0.1
    names = ["left_drive_a_wheel_joint", "right_drive_a_wheel_joint"]
    b.t.handlers["/agv/joint_commands"](joint_command(["caster", *names], [9.0, left, right]))
    b.t.handlers["/agv/cmd_vel"](twist_msg(*TWIST))
    assert feed.twists[0] == pytest.approx(feed.twists[1])  # one decision, one source
    before = len(feed.twists)
    for bad in (
        joint_command(names[:1], [left]),  # a wheel without a velocity
        joint_command(names, [left, math.nan]),
        joint_command(names, [left]),
    ):
        b.t.handlers["/agv/joint_commands"](bad)
    assert len(feed.twists) == before  # refused: nothing reached the robot


def test_joint_commands_drive_the_wheels_and_silence_stops_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    b = agv(monkeypatch)
    robot = b.robot()
    drive(b, 0.3, None)
    names = ["left_drive_a_wheel_joint", "right_drive_a_wheel_joint"]
    wheel = [(TWIST[0] - TWIST[1] * 0.225) / 0.1, (TWIST[0] + TWIST[1] * 0.225) / 0.1]
    handler = b.t.handlers["/agv/joint_commands"]
    drive(b, 1.0, lambda: handler(joint_command(names, wheel)))
    for w, rad_s in zip(robot.wheels, wheel, strict=True):
        motor = w.motor_speed(rad_s * 0.1)
        assert b.motor(w.unit, w.axis) == pytest.approx(motor, rel=0.01)
    assert b.rig.sup.arbiter.owner("left_drive") == "ros2:agv/cmd_vel"  # cmd_vel's source
    drive(b, 0.4, None)  # quiet longer than command_timeout_ms (300): zero commanded
    assert all(b.rig.drive(u).cmd_raw == (0, 0) for u in robot.units)
    assert b.rig.sup.arbiter.owner("left_drive") is None


# ---------------------------------------------------------------- 5. stamped


def stamped(linear: float, angular: float, age: float) -> Any:
    ns = time.time_ns() - int(age * 1e9)
    return types.TwistStamped(
        types.Header(types.Time(ns // 10**9, ns % 10**9), "base_link"), twist_msg(linear, angular)
    )


@pytest.mark.parametrize(
    ("extra", "stamped_type"),
    [
        ("", False),
        (", distro: humble", False),
        (", distro: kilted", True),
        (", distro: rolling", True),
        (", distro: kilted, cmd_vel_stamped: false", False),
        (", robots: {agv: {cmd_vel_stamped: true}}", True),
    ],
)
def test_cmd_vel_is_stamped_as_the_distros_nav2_publishes_it(
    monkeypatch: pytest.MonkeyPatch, extra: str, stamped_type: bool
) -> None:
    b = agv(monkeypatch, extra=extra)
    topics: RobotTopics = b.plugin.robots["agv"].topics
    feed = RecordingFeed()
    topics.feed = lambda: feed  # type: ignore[assignment,return-value]
    handler = b.t.handlers["/agv/cmd_vel"]
    if stamped_type:
        handler(stamped(*TWIST, age=0.01))
        handler(stamped(*TWIST, age=0.31))  # older than command_timeout_ms: stale, refused
        handler(types.TwistStamped())  # no stamp at all: as old as can be
    else:
        handler(twist_msg(*TWIST))
    assert feed.twists == [TWIST]
