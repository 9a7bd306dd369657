"""The ROS 2 bridge's ``cmd_vel`` and ``odom`` per robot, on the fake clock: the plugin on
an in-memory transport, the supervisor and simulated drives of tests/support/rig.py.

A two-drive robot (one wheel per drive, the right one mounted mirrored), a skid-steer on
two drives and a robot declared on one drive (its left motor mirrored): a ``cmd_vel``
moves every wheel, in the same scheduler turn, with its mounting's sign; ``odom`` from
every wheel follows the motion the simulated drives made.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest

pytest.importorskip("cyclonedds")
from abh3_plugins.ros2 import types
from abh3_plugins.ros2.robot import source_name
from abh3_plugins.ros2.settings import Settings
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.robot import Side
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_host.host import PluginHost
from tests.support.robot_truth import Truth
from tests.support.ros2_rig import Bridged

UNITS = """
buses: {{b: {{interface: virtual, channel: robot, simulate: true}}}}
units:
{units}
robots:
  - name: {name}
    track_m: {track}
    diameter_m: 0.2
    gear_ratio: 10
    pulses_per_rev: 4096
    frame_id: world
    child_frame_id: {name}_base
    wheels:
{wheels}
"""
UNIT = "  - {{name: {0}, abh3_id: {1}, broadcast: {{mask: 0x13, rate_hz: 50}}}}"
TWO_DRIVES = UNITS.format(
    units="\n".join([UNIT.format("l", 1), UNIT.format("r", 3)]),
    name="rover",
    track=0.5,
    wheels="      - {unit: l, axis: A, side: left}\n"
    "      - {unit: r, axis: A, side: right, sign: -1}",
)
SKID = UNITS.format(
    units="\n".join([UNIT.format("front", 1), UNIT.format("rear", 3)]),
    name="skid",
    track=0.6,
    wheels="\n".join(
        f"      - {{unit: {u}, axis: {a}, side: {s}}}"
        for u in ("front", "rear")
        for a, s in (("A", "left"), ("B", "right"))
    ),
)
ONE_DRIVE = UNITS.format(  # declared on one drive: the robot's names, not the unit's
    units=UNIT.format("base", 1),
    name="cart",
    track=0.4,
    wheels="      - {unit: base, axis: A, side: left, sign: -1}\n"
    "      - {unit: base, axis: B, side: right}",
)
TWIST = (0.2, 0.5)


def bridging(text: str, monkeypatch: pytest.MonkeyPatch) -> Bridged:
    """The rig these tests share: commands allowed, no periodic diagnostics."""
    return Bridged(text, monkeypatch, settings=Settings(allow_commands=True, diagnostics_hz=0.0))


@pytest.fixture(
    params=[TWO_DRIVES, SKID, ONE_DRIVE], ids=["two-drives", "skid-steer", "one-drive-declared"]
)
def bridged(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[Bridged]:
    b = bridging(request.param, monkeypatch)
    yield b
    b.plugin.abh3_stop()


def test_one_cmd_vel_and_one_odom_per_robot_under_its_name(bridged: Bridged) -> None:
    robot = bridged.robot()
    t = bridged.t
    assert f"/{robot.name}/cmd_vel" in t.handlers
    assert f"/{robot.name}/odom" in t.published
    for unit in robot.units:  # the seed's per-unit names stay; the pair is the robot's
        assert f"/{unit}/vel_cmd" in t.handlers and f"/{unit}/brd_num" in t.handlers
        assert f"/{unit}/cmd_vel" not in t.handlers and f"/{unit}/odom" not in t.published
    source = bridged.sources[source_name(robot.name)]
    assert source.units == robot.units  # its twist is the whole robot's


def test_cmd_vel_moves_every_wheel_in_one_turn_and_odom_follows_the_motion(
    bridged: Bridged,
) -> None:
    robot, rig = bridged.robot(), bridged.rig
    rig.run(0.5)  # the drives report; odometry's origin
    cmd_vel = bridged.t.handlers[f"/{robot.name}/cmd_vel"]
    odom = bridged.t.published[f"/{robot.name}/odom"]
    assert odom and odom[-1].pose.pose.position.x == 0.0
    wheels = [(w.unit, w.axis) for w in robot.wheels]
    first_command: dict[str, float] = {}
    truth = Truth(robot, bridged.motor)  # where it really went
    start = rig.timeline.now
    step = 0.001
    for i in range(3000):  # 3 s of cmd_vel at 20 Hz, then 1 s of silence (zero)
        if i < 2000 and i % 50 == 0:
            cmd_vel(types.Twist(types.Vector3(TWIST[0]), types.Vector3(z=TWIST[1])))
        rig.run(step)
        for unit in robot.units:
            if unit not in first_command and rig.drive(unit).cmd_raw != (0, 0):
                first_command[unit] = rig.timeline.now
        truth.step(step)
        if i == 1900:  # at speed: every wheel turns with its mounting's sign
            expected = {
                (w.unit, w.axis): w.motor_speed(
                    TWIST[0] + (1 if w.side is Side.RIGHT else -1) * TWIST[1] * robot.track_m / 2
                )
                for w in robot.wheels
            }
            for key in wheels:
                assert bridged.motor(*key) == pytest.approx(expected[key], rel=0.01), key
            if robot.name == "rover":
                assert bridged.motor("r", 0) < 0 < bridged.motor("l", 0)  # mirrored right
                assert bridged.motor("l", 1) == bridged.motor("r", 1) == 0.0  # no wheel on B
            moving = odom[-1]
            assert moving.twist.twist.linear.x == pytest.approx(TWIST[0], rel=0.01)
            assert moving.twist.twist.angular.z == pytest.approx(TWIST[1], rel=0.01)
    # both drives got their first command in the same scheduler turn (20 ms apart otherwise)
    assert set(first_command) == set(robot.units)
    assert max(first_command.values()) - min(first_command.values()) < 0.002
    assert first_command[robot.units[0]] - start < 0.05
    assert all(bridged.motor(*key) == 0.0 for key in wheels)  # silence: zero
    last = odom[-1]
    assert (last.header.frame_id, last.child_frame_id) == ("world", f"{robot.name}_base")
    # the truth moved: 0.5 rad/s from the first cmd_vel to 0.5 s (the timeout) after the last
    assert truth.yaw == pytest.approx(0.5 * (1.95 + 0.5), rel=0.03)
    got = last.pose.pose
    got_yaw = 2 * math.atan2(got.orientation.z, got.orientation.w)
    assert got_yaw == pytest.approx(truth.yaw, abs=0.01)
    assert (got.position.x, got.position.y) == pytest.approx((truth.x, truth.y), abs=0.005)


def test_a_cmd_vel_beyond_what_a_wheels_frame_can_carry_is_clamped_as_a_whole(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """One rule at every entry (docs/safety.md): beyond the limits or the wire's range a
    twist is scaled down as a whole, its curvature kept, and said — as the socket's is."""
    b = bridging(TWO_DRIVES, monkeypatch)
    cmd_vel = b.t.handlers["/rover/cmd_vel"]
    # straight at 6 m/s needs ±5730 min⁻¹; turning at 10 rad/s on top, the right wheel
    # needs more than 6553.4: both wheels are scaled by one factor
    cmd_vel(types.Twist(types.Vector3(6.0), types.Vector3(z=10.0)))
    b.rig.run(0.1)
    left, right = (abs(b.rig.drive(u).cmd_raw[0]) for u in ("l", "r"))
    assert 0 < left < right <= 32767
    assert right / left == pytest.approx((6.0 + 10.0 * 0.25) / (6.0 - 10.0 * 0.25), rel=0.01)
    assert not any("cmd_vel refused" in r.message for r in caplog.records)
    b.plugin.abh3_stop()


def test_a_one_drive_robot_keeps_the_units_names_source_and_frames(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text = TWO_DRIVES.replace(
        "robots:",
        "  - {name: solo, abh3_id: 4, broadcast: {mask: 0x13, rate_hz: 50},\n"
        "     geometry: {pulses_per_rev: 4096}}\nrobots:",
    )
    b = bridging(text, monkeypatch)
    assert {"/solo/cmd_vel", "/rover/cmd_vel"} <= set(b.t.handlers)
    assert "ros2:solo" in b.sources and source_name("rover") in b.sources
    b.rig.run(0.3)
    b.t.handlers["/solo/cmd_vel"](types.Twist(types.Vector3(0.1), types.Vector3()))
    b.rig.run(0.3)
    assert b.rig.sup.arbiter.owner("solo") == "ros2:solo"  # shared with its vel_cmd, as before
    assert b.rig.sup.arbiter.owner("l") is None  # another robot
    solo = b.t.published["/solo/odom"][-1]
    assert (solo.header.frame_id, solo.child_frame_id) == ("odom", "base_link")  # settings'
    b.plugin.abh3_stop()


def test_a_robots_odom_must_not_collide_with_a_units() -> None:
    ok = TWO_DRIVES + "plugins:\n  ros2: {remap: {rover/odom: /rover/wheel_odom}}\n"
    PluginHost(parse_config(ok, "r.yaml"))
    text = TWO_DRIVES + "plugins:\n  ros2: {remap: {rover/odom: /l/vel_fbk_ab}}\n"
    with pytest.raises(ConfigError, match="unit l and robot rover would both publish /l/vel_fbk"):
        PluginHost(parse_config(text, "r.yaml"))
