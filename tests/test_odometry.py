"""Dead reckoning from pulse counts: formulas, wrap-around, agreement with the twist, and a
robot's odometry from every wheel (rounds across units, mirrored wheels, side means)."""

from __future__ import annotations

import itertools
import math
import random

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.kinematics import Geometry, yx_to_twist
from abh3_supervisor.core.odometry import (
    Odometer,
    Pose,
    PulseOdometry,
    RobotOdometry,
    odometers,
    yaw_quaternion,
)
from abh3_supervisor.core.robot import RobotConfig, Side, Wheel, from_geometry
from abh3_supervisor.core.state import Feedback
from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.core import StatusEvent
from abh3_supervisor.simulator.drive import PULSES_PER_REV
from tests.support.rig import Rig, present, set_twist

G = Geometry(pulses_per_rev=1000)  # 1 pulse = 0.1 / 10 · 0.1 · π / 1000 m


def test_straight_line_and_turn_in_place() -> None:
    odo = PulseOdometry(G)
    odo.update(0, 0)
    pose = odo.update(1000, 1000)  # one motor revolution on both wheels
    assert (pose.x, pose.y, pose.yaw) == pytest.approx((G.metres_per_motor_rev, 0, 0))
    quarter = math.pi / 2 * G.width / 2 / odo.metres_per_pulse  # each wheel's pulses
    odo = PulseOdometry(G)
    odo.update(0, 0)
    pose = odo.update(round(-quarter), round(quarter))  # right wheel forward: counter-clockwise
    assert pose.yaw == pytest.approx(math.pi / 2, rel=1e-3)
    assert math.hypot(pose.x, pose.y) == pytest.approx(0, abs=1e-9)


def test_counter_wrap_is_a_small_step() -> None:
    odo = PulseOdometry(G)
    odo.update(2**31 - 10, -(2**31) + 5)
    pose = odo.update(-(2**31) + 10, 2**31 - 5)  # +20 on A across the top, −10 on B
    assert pose.x == pytest.approx(5 * odo.metres_per_pulse)


def test_needs_pulses_per_rev() -> None:
    with pytest.raises(ValueError, match="pulses_per_rev"):
        PulseOdometry(Geometry())


def test_quaternion_of_a_yaw() -> None:
    x, y, z, w = yaw_quaternion(math.pi / 2)
    assert x == y == 0 and z * z + w * w == pytest.approx(1)
    assert 2 * math.atan2(z, w) == pytest.approx(math.pi / 2)


def test_odometry_follows_a_commanded_twist_on_the_simulated_drive() -> None:
    """Drive an arc for 4 s: the pulses integrate to what the twist says, signs included."""
    cfg = parse_config(
        "buses: {b: {interface: virtual, channel: t, simulate: true}}\n"
        "units: [{name: u, broadcast: {mask: 0x10, rate_hz: 50},\n"
        f"  geometry: {{pulses_per_rev: {PULSES_PER_REV}}},\n"
        "  startup: ['SERVO ON ON', 'START ON ON']}]\n",
        "c.yaml",
    )
    rig = Rig(cfg)
    for text in cfg.units["u"].startup:
        rig.sup.apply_text("u", text)
    odo = PulseOdometry(cfg.units["u"].geometry)

    def on_event(event: object) -> None:
        if isinstance(event, StatusEvent) and isinstance(event.record, frames.Brd4):
            odo.update(event.record.pulse_a, event.record.pulse_b)

    rig.sup.subscribe(on_event)
    rig.run(0.5)  # first reading: the origin
    set_twist(rig.sup, "u", 0.1, 0.2, source=present(rig.sup, "u"))
    rig.run(1.0)  # ramp
    start = odo.pose
    rig.run(4.0)
    pose = odo.pose
    assert pose.yaw - start.yaw == pytest.approx(0.8, rel=0.02)  # 0.2 rad/s · 4 s, CCW
    chord = math.hypot(pose.x - start.x, pose.y - start.y)
    radius = 0.1 / 0.2
    assert chord == pytest.approx(2 * radius * math.sin(0.4), rel=0.02)


# ---------------------------------------------------------------- a robot, every wheel

D, GEAR, PPR = 0.2, 10.0, 1000.0
MPP = math.pi * D / GEAR / PPR  # metres per pulse of every wheel below
TWO_DRIVES = RobotConfig(  # one wheel per drive, the right one mounted mirrored
    "rover",
    (
        Wheel("l", 0, Side.LEFT, D, GEAR, 1, PPR),
        Wheel("r", 0, Side.RIGHT, D, GEAR, -1, PPR),
    ),
    0.5,
)
SKID = RobotConfig(  # four wheels on two drives: front A/B, rear A/B
    "skid",
    tuple(
        Wheel(unit, axis, side, D, GEAR, 1, PPR)
        for unit in ("front", "rear")
        for axis, side in ((0, Side.LEFT), (1, Side.RIGHT))
    ),
    0.6,
)


def test_a_round_waits_for_every_unit_and_counts_each_wheel_once() -> None:
    odo = RobotOdometry(TWO_DRIVES)
    assert odo.update("l", 5, 0) is None  # the right drive has not reported: no origin yet
    assert odo.update("r", -7, 0) == Pose()  # both: the origin
    assert odo.update("l", 505, 0) is None
    assert odo.update("l", 1005, 0) is None  # a faster unit: its count moves on, nothing lost
    pose = odo.update("r", -1007, 0)  # mirrored: counting down is rolling forward
    assert pose is not None
    assert (pose.x, pose.y, pose.yaw) == pytest.approx((1000 * MPP, 0, 0))
    assert odo.update("elsewhere", 1, 1) is None  # not a unit of the robot


def test_a_mirrored_wheel_turns_the_robot_the_right_way() -> None:
    odo = RobotOdometry(TWO_DRIVES)
    odo.update("l", 0, 0)
    odo.update("r", 0, 0)
    quarter = round(math.pi / 2 * 0.5 / 2 / MPP)  # each wheel's pulses for 90°
    odo.update("l", -quarter, 0)  # left back
    pose = odo.update("r", -quarter, 0)  # right (mirrored) forward: counter-clockwise
    assert pose is not None
    assert pose.yaw == pytest.approx(math.pi / 2, rel=1e-3)
    assert math.hypot(pose.x, pose.y) == pytest.approx(0, abs=1e-9)


def test_skid_steer_sides_are_the_mean_of_their_wheels_across_a_wrap() -> None:
    odo = RobotOdometry(SKID)
    top = 2**31 - 100
    odo.update("front", top, 0)
    odo.update("rear", 0, 0)
    odo.update("front", -(2**31) + 1100, 1000)  # left +1200 across the wrap, right +1000
    pose = odo.update("rear", 800, 1000)  # left +800, right +1000
    assert pose is not None
    left, right = 1000 * MPP, 1000 * MPP  # each side's mean
    assert (pose.x, pose.yaw) == pytest.approx(((left + right) / 2, 0.0))


def test_needs_every_wheels_pulses_per_rev() -> None:
    blind = RobotConfig("blind", (*TWO_DRIVES.wheels[:1], Wheel("r", 0, Side.RIGHT, D)), 0.5)
    with pytest.raises(ValueError, match="pulses_per_rev"):
        RobotOdometry(blind)


def _seed_pose(readings: list[tuple[int, int]], g: Geometry) -> tuple[float, float, float]:
    """The one-drive integration as it was before robots, for the bit-for-bit check."""
    mpp, x, y, yaw = g.metres_per_motor_rev / g.pulses_per_rev, 0.0, 0.0, 0.0
    for (a0, b0), (a1, b1) in itertools.pairwise(readings):
        left, right = _step_of(a1, a0) * mpp, _step_of(b1, b0) * mpp
        distance, turn = (left + right) / 2, (right - left) / g.width
        heading = yaw + turn / 2
        x, y = x + distance * math.cos(heading), y + distance * math.sin(heading)
        yaw = math.atan2(math.sin(yaw + turn), math.cos(yaw + turn))
    return x, y, yaw


def _step_of(new: int, old: int) -> int:
    return (new - old + (1 << 31)) % (1 << 32) - (1 << 31)


def test_a_one_drive_robot_keeps_the_seeds_arithmetic_to_the_bit() -> None:
    rng = random.Random(30)
    g = Geometry(rate_num=3, rate_den=17, wheel=0.137, width=0.41, pulses_per_rev=4096)
    readings, a, b = [], 0, 0
    for _ in range(2000):
        a += rng.randint(-300, 900)
        b += rng.randint(-300, 900)
        readings.append((a, b))
    odo = PulseOdometry(g)
    odometer = Odometer(from_geometry("u", g), g)
    for ra, rb in readings:
        pose = odo.update(ra, rb)
        assert odometer.pulses("u", ra, rb) == pose  # every report: one round
    assert (pose.x, pose.y, pose.yaw) == _seed_pose(readings, g)  # exact, not approx


def test_the_twist_counts_every_wheels_feedback() -> None:
    speed = 60.0 / (math.pi * D / GEAR)  # min⁻¹ for 1 m/s
    odometer = Odometer(TWO_DRIVES)
    assert odometer.twist({"l": Feedback(0, speed, 0, 0, 0), "r": None}) == (0.0, 0.0)
    fb = {"l": Feedback(0, speed, 0, 0, 0), "r": Feedback(0, -speed, 0, 0, 0)}
    assert odometer.twist(fb) == pytest.approx((1.0, 0.0))  # mirrored right: forward too
    fb["r"] = Feedback(0, -2 * speed, 0, 0, 0)
    assert odometer.twist(fb) == pytest.approx((1.5, 1.0 / 0.5))
    g = Geometry(pulses_per_rev=1000)
    seed = Odometer(from_geometry("u", g), g)
    fbk = Feedback(0, 300.0, 100.0, 200.0, 100.0)
    assert seed.twist({"u": fbk}) == yx_to_twist(200.0, 100.0, g)  # the seed's, to the bit


def test_every_robot_with_known_pulses_and_every_monitor_unit_with_geometry() -> None:
    cfg = parse_config(
        "buses: {b: {interface: virtual, channel: t, simulate: true}}\n"
        "units:\n"
        "  - {name: l, abh3_id: 1}\n"
        "  - {name: r, abh3_id: 6}\n"
        "  - {name: solo, abh3_id: 3, geometry: {pulses_per_rev: 4096}}\n"
        "  - {name: plain, abh3_id: 4}\n"
        "  - {name: eye, abh3_id: 5, role: monitor, geometry: {pulses_per_rev: 100}}\n"
        "robots:\n"
        "  - name: rover\n"
        "    track_m: 0.5\n"
        "    diameter_m: 0.2\n"
        "    pulses_per_rev: 4096\n"
        "    wheels:\n"
        "      - {unit: l, axis: A, side: left}\n"
        "      - {unit: r, axis: A, side: right, sign: -1}\n",
        "c.yaml",
    )
    found = {o.robot.name: o for o in odometers(cfg)}
    assert set(found) == {"rover", "solo", "eye"}  # plain has no pulses_per_rev
    assert found["rover"].geometry is None and found["rover"].units == ("l", "r")
    assert found["solo"].geometry == cfg.units["solo"].geometry


def test_units_at_different_rates_are_compared_at_one_instant() -> None:
    """Straight ahead at a steady speed, the left drive reporting at 50 Hz and the right
    at 20 Hz (its clock a little off): every pose is straight, at the round's distance."""
    rate = 10_000.0  # pulses per second on each wheel
    reports = [(i * 0.02, "l") for i in range(100)] + [(0.003 + i * 0.05, "r") for i in range(40)]
    odo = RobotOdometry(TWO_DRIVES)
    poses, latest = [], {}
    for t, unit in sorted(reports):
        count = round(rate * t) * (1 if unit == "l" else -1)  # the right wheel is mirrored
        latest[unit] = t
        pose = odo.update(unit, count, 0, t)
        if pose is not None:
            poses.append((min(latest.values()), pose))  # a round's time: the earliest latest
    assert 38 <= len(poses) <= 40  # a round per report of the slower drive
    (t0, start), (t1, end) = poses[0], poses[-1]
    assert t0 == 0.003  # the origin: once both had reported
    for _, pose in poses:
        assert pose.yaw == pytest.approx(0.0, abs=2 * MPP / 0.5)  # counts round to a pulse
        assert pose.y == pytest.approx(0.0, abs=1e-6)
    assert end.x - start.x == pytest.approx(rate * (t1 - t0) * MPP, abs=2 * MPP)


def test_a_silent_drive_costs_no_memory_and_the_pose_waits_for_it() -> None:
    odo = RobotOdometry(TWO_DRIVES)
    odo.update("l", 0, 0, 0.0)
    odo.update("r", 0, 0, 0.0)
    for i in range(1, 5001):  # the right drive went silent: no round, nothing kept
        assert odo.update("l", i, 0, i * 0.02) is None
    assert max(len(r) for r in odo._reports.values()) <= 2
    pose = odo.update("r", -5000, 0, 100.0)  # back: its whole travel counts at once
    assert pose is not None
    assert (pose.x, pose.yaw) == pytest.approx((5000 * MPP, 0.0))
