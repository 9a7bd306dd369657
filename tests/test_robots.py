"""A robot as a whole on a fake clock: one decision for all its drives, read off the wire."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.advice import warnings
from abh3_supervisor.core.commands import VelocityCommand
from abh3_supervisor.core.inputs import Twist
from abh3_supervisor.core.kinematics import twist_to_ab
from abh3_supervisor.core.robot import Side, motor_speeds, twist_of
from abh3_supervisor.core.supervisor import Notice
from abh3_supervisor.errors import CommandError, ConfigError
from abh3_supervisor.protocol import frames, ids
from tests.support.rig import Rig, present, set_twist, set_velocity

UNITS = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: l, abh3_id: 1, velocity_model: motor}
  - {name: r, abh3_id: 3, protocol: "2023", velocity_model: motor}
"""
# one wheel per drive; the right motor is mounted mirrored
ONE_PER_DRIVE = (
    UNITS
    + """
robots:
  - name: rover
    track_m: 0.5
    diameter_m: 0.2
    gear_ratio: 10
    wheels:
      - {unit: l, axis: A, side: left}
      - {unit: r, axis: A, side: right, sign: -1}
"""
)
# skid-steer on two drives: the left drive's A front and B rear, the right one mirrored
SKID_STEER = (
    UNITS
    + """
robots:
  - name: skid
    track_m: 0.6
    diameter_m: 0.25
    gear_ratio: 20
    wheels:
      - {unit: l, axis: A, side: left}
      - {unit: l, axis: B, side: left}
      - {unit: r, axis: A, side: right, sign: -1}
      - {unit: r, axis: B, side: right, sign: -1}
"""
)


def rig_of(text: str) -> Rig:
    rig = Rig(parse_config(text, "robot.yaml"))
    for unit in rig.config.units:
        assert rig.sup.apply_text(unit, "SERVO ON ON") == ""
        assert rig.sup.apply_text(unit, "START ON ON") == ""
    return rig


def commands(rig: Rig, unit: str) -> list[tuple[float, float, float]]:
    """(start, AY, BX) of every DP0 command frame ``unit``'s drive was sent."""
    cfg = rig.config.units[unit]
    out = []
    for f in rig.timeline.frames:
        if f.arbitration_id == ids.dp0_command_id(cfg.abh3_id, cfg.host_id):
            cmd = frames.decode_dp0_command(f.data, cfg.protocol)
            assert isinstance(cmd, frames.Dp0Command)
            out.append((f.start, cmd.cmd_ay, cmd.cmd_bx))
    return out


def first_moving(rig: Rig, unit: str, after: float) -> tuple[float, float, float]:
    return next(c for c in commands(rig, unit) if c[0] >= after and (c[1] or c[2]))


def per_min(mps: float, diameter: float, gear: float) -> float:
    return mps * 60 / (math.pi * diameter / gear)


def test_one_wheel_per_drive_goes_straight_with_the_mirrored_motor_backwards() -> None:
    rig = rig_of(ONE_PER_DRIVE)
    rig.run(0.1)
    set_twist(rig.sup, "rover", 0.3, 0.0, source=present(rig.sup, "l"))
    rig.run(1.5)
    speed = per_min(0.3, 0.2, 10)
    _, la, lb = commands(rig, "l")[-1]
    _, ra, rb = commands(rig, "r")[-1]
    assert (la, lb) == pytest.approx((speed, 0.0), abs=0.1)
    assert (ra, rb) == pytest.approx((-speed, 0.0), abs=0.1)
    # the simulated motors turn so: the robot goes straight at 0.3 m/s
    robot = rig.config.robots["rover"]
    turning = {("l", 0): rig.drive("l").vel[0], ("r", 0): rig.drive("r").vel[0]}
    assert twist_of(robot, turning) == pytest.approx((0.3, 0.0), abs=1e-3)


def test_skid_steer_turns_every_wheel_of_a_side_alike() -> None:
    rig = rig_of(SKID_STEER)
    rig.run(0.1)
    set_twist(rig.sup, "skid", 0.0, 1.0, source=present(rig.sup, "r"))  # on the spot
    rig.run(1.5)
    wheel = per_min(1.0 * 0.6 / 2, 0.25, 20)
    assert commands(rig, "l")[-1][1:] == pytest.approx((-wheel, -wheel), abs=0.1)
    # right side forward, its motors mirrored
    assert commands(rig, "r")[-1][1:] == pytest.approx((-wheel, -wheel), abs=0.1)


def test_a_robots_drives_get_their_speeds_in_the_same_scheduler_turn() -> None:
    rig = rig_of(ONE_PER_DRIVE)
    rig.run(0.2)
    t = rig.timeline.now
    set_twist(rig.sup, "rover", 0.3, 0.5, source=present(rig.sup, "l"))
    rig.run(0.2)
    left, right = first_moving(rig, "l", t), first_moving(rig, "r", t)
    assert left[0] == right[0]  # one turn: the same instant on the fake clock
    # and every turn after: the two drives never differ in phase
    starts_l = [c[0] for c in commands(rig, "l")]
    starts_r = [c[0] for c in commands(rig, "r")]
    assert starts_l == starts_r


def test_units_of_no_common_robot_share_a_turn_unless_the_bus_says_one_per_turn() -> None:
    rig = rig_of(UNITS)  # the default: up to 4 units in a turn
    rig.run(0.2)
    assert [c[0] for c in commands(rig, "l")] == [c[0] for c in commands(rig, "r")]
    apart = rig_of(UNITS.replace("simulate: true}", "simulate: true, units_per_turn: 1}"))
    apart.run(0.2)
    starts_l = [c[0] for c in commands(apart, "l")]
    starts_r = [c[0] for c in commands(apart, "r")]
    assert starts_l[0] != starts_r[0]
    # half a period apart, every period
    period = 1 / apart.config.units["l"].command_rate_hz
    pairs = zip(starts_l, starts_r, strict=False)
    assert all(right - left == pytest.approx(period / 2) for left, right in pairs)


def test_one_saturated_side_slows_the_whole_robot_and_it_goes_straight() -> None:
    limited = ONE_PER_DRIVE.replace(
        "velocity_model: motor}\n", "velocity_model: motor, limits: {velocity: 100}}\n", 1
    )
    rig = rig_of(limited)
    result = set_twist(rig.sup, "rover", 1.0, 0.0, source=present(rig.sup, "l"))
    rig.run(1.0)
    la, ra = commands(rig, "l")[-1][1], commands(rig, "r")[-1][1]
    assert la == pytest.approx(100.0, abs=0.1)
    assert ra == pytest.approx(-100.0, abs=0.1)  # the unlimited side slowed alike
    assert result.clamped
    notes = [e.message for e in rig.events if isinstance(e, Notice)]
    assert any(n.startswith("robot rover: twist 1 0 →") and "axis" in n for n in notes)


def test_robot_limits_scale_the_twist_and_keep_its_path() -> None:
    text = ONE_PER_DRIVE.replace(
        "    gear_ratio: 10\n",
        "    gear_ratio: 10\n    limits: {linear_mps: 0.5, angular_radps: 1.0}\n",
    )
    rig = rig_of(text)
    set_twist(rig.sup, "rover", 1.0, 1.0, source=present(rig.sup, "l"))
    plan = rig.sup.robots["rover"].last
    assert plan is not None
    assert plan.twist == pytest.approx((0.5, 0.5))  # curvature 1 m⁻¹ kept
    assert "limits.linear_mps 0.5" in (plan.note or "")


def test_robot_limits_bound_each_axis_for_unit_commands_too() -> None:
    text = ONE_PER_DRIVE.replace(
        "    gear_ratio: 10\n",
        "    gear_ratio: 10\n    limits: {linear_mps: 0.5, angular_radps: 1.0}\n",
    )
    rig = rig_of(text)
    fastest = per_min(0.5 + 1.0 * 0.5 / 2, 0.2, 10)  # the fastest wheel within the limits
    assert rig.sup.units["l"].axis_limits == pytest.approx((fastest, math.inf))
    result = set_velocity(rig.sup, "l", 5000, 0, source=present(rig.sup, "l"))
    assert result.ay == pytest.approx(fastest)
    assert result.clamped


def test_acceleration_ramps_up_and_a_stop_is_at_once() -> None:
    text = ONE_PER_DRIVE.replace(
        "    gear_ratio: 10\n", "    gear_ratio: 10\n    limits: {linear_accel_mps2: 0.5}\n"
    )
    rig = rig_of(text)
    rig.run(0.1)
    source = present(rig.sup, "l")
    set_twist(rig.sup, "rover", 0.5, 0.0, source=source)
    rig.run(0.5)
    halfway = rig.sup.robots["rover"].last
    assert halfway is not None and 0.2 < halfway.twist[0] < 0.3  # 0.5 m/s² for 0.5 s
    rig.run(0.7)
    assert rig.sup.robots["rover"].last.twist[0] == pytest.approx(0.5)  # type: ignore[union-attr]
    assert commands(rig, "l")[-1][1] == pytest.approx(per_min(0.5, 0.2, 10), abs=0.1)
    t = rig.timeline.now
    rig.sup.arbiter.submit(source, None, t)  # released: zero at once, on both drives
    assert rig.sup.units["l"].setpoint.ay == 0 and rig.sup.units["r"].setpoint.ay == 0


def test_a_unit_that_stops_stops_its_whole_robot() -> None:
    rig = rig_of(ONE_PER_DRIVE)
    set_twist(rig.sup, "rover", 0.3, 0.0, source=present(rig.sup, "l"))
    assert rig.sup.units["r"].setpoint.ay != 0
    rig.sup.zero("l")  # as a gap or an offline drive does
    assert rig.sup.units["r"].setpoint.ay == 0
    assert rig.sup.arbiter.owner("r") is None


def test_a_unit_that_refuses_leaves_the_whole_robot_still() -> None:
    rig = rig_of(ONE_PER_DRIVE)
    source = present(rig.sup, "l")
    assert rig.sup.apply_text("r", "TORQUE ON ON") == ""  # r takes currents, not speeds
    with pytest.raises(CommandError, match="current mode"):
        set_twist(rig.sup, "rover", 0.3, 0.0, source=source)
    rig.sup.arbiter.submit(source, Twist(0.3, 0.0), 0.0)  # a stream: refused on r
    assert rig.sup.units["l"].setpoint.ay == 0 and rig.sup.units["r"].setpoint.ay == 0
    assert rig.sup.arbiter.owner("l") is None


def test_a_robot_has_one_owner_another_sources_unit_command_zeroes_the_rest() -> None:
    rig = rig_of(ONE_PER_DRIVE)
    set_twist(rig.sup, "rover", 0.3, 0.0, source=present(rig.sup, "l"))
    other = present(rig.sup, "r")
    rig.sup.arbiter.sources[other].priority = 5
    rig.sup.arbiter.submit(other, VelocityCommand(50, 0), 1.0)  # r's A (its wheel) only
    assert rig.sup.units["l"].setpoint.ay == 0  # not half a robot on the old twist
    assert (rig.sup.units["r"].setpoint.ay, rig.sup.units["r"].setpoint.bx) == (50, 0)


def test_a_file_without_robots_twists_each_unit_as_the_seed_does() -> None:
    rig = rig_of(UNITS)
    result = set_twist(rig.sup, "l", 0.05, 0.1, source=present(rig.sup, "l"))
    geometry = rig.config.units["l"].geometry
    assert (result.ay, result.bx) == pytest.approx(twist_to_ab(0.05, 0.1, geometry))
    assert rig.config.robots["l"].implicit
    # and the robot's kinematics agree with the seed's formulas
    assert motor_speeds(rig.config.robots["l"], 0.05, 0.1)["l"] == pytest.approx(
        twist_to_ab(0.05, 0.1, geometry)
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("diameter_m: 0.2", "radius_m: 0.1"), "give diameter_m, the wheel's DIAMETER"),
        (
            ("{unit: r, axis: A, side: right, sign: -1}", "{unit: r, axis: A, side: left}"),
            "no wheel on the right side",
        ),
        (("sign: -1", "sign: 2"), "expected 1 (mounted forward) or -1"),
        (("{unit: r, axis: A", "{unit: x, axis: A"), "no unit named 'x'"),
        (("track_m: 0.5", "trak_m: 0.5"), "did you mean 'track_m'"),
    ],
)
def test_robot_mistakes_are_named_with_file_and_line(change: tuple[str, str], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(ONE_PER_DRIVE.replace(*change), "robot.yaml")
    assert message in str(info.value)
    assert "robot.yaml:" in str(info.value)


def test_a_unit_drives_one_robot_and_has_no_geometry_of_its_own() -> None:
    twice = (
        ONE_PER_DRIVE
        + """
  - name: again
    track_m: 0.5
    diameter_m: 0.2
    wheels:
      - {unit: l, axis: B, side: left}
      - {unit: r, axis: B, side: right}
"""
    )
    with pytest.raises(ConfigError, match="unit 'l' already drives robot 'rover'"):
        parse_config(twice, "robot.yaml")
    geometry = ONE_PER_DRIVE.replace(
        "velocity_model: motor}", "velocity_model: motor, geometry: {wheel: 0.2}}", 1
    )
    with pytest.raises(ConfigError, match="remove its geometry"):
        parse_config(geometry, "robot.yaml")


def test_a_radius_in_geometry_points_at_wheel_the_diameter() -> None:
    text = UNITS.replace(
        "velocity_model: motor}", "velocity_model: motor, geometry: {wheel_radius: 0.1}}", 1
    )
    with pytest.raises(ConfigError, match="give wheel, the wheel's DIAMETER"):
        parse_config(text, "robot.yaml")


def test_a_robots_drives_on_one_bus_share_one_command_rate() -> None:
    text = ONE_PER_DRIVE.replace(
        "{name: r, abh3_id: 3,", "{name: r, abh3_id: 3, command_rate_hz: 40,"
    )
    with pytest.raises(ConfigError, match="give them one rate"):
        parse_config(text, "robot.yaml")


def robot_docs_files() -> list[str]:
    text = (Path(__file__).parent.parent / "docs" / "robots.md").read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, re.S)
    return [b for b in blocks if b.startswith("buses:")]


def test_the_docs_three_shapes_are_complete_files_check_passes_without_warning() -> None:
    files = robot_docs_files()
    assert len(files) == 3
    for text in files:
        config = parse_config(text, "docs/robots.md")
        assert warnings(config) == []
        (robot,) = [r for r in config.robots.values() if not r.implicit]
        assert {w.side for w in robot.wheels} == set(Side)


def test_real_bus_without_limits_or_with_startup_motion_is_warned_with_its_line() -> None:
    real = UNITS.replace(
        "interface: virtual, channel: t, simulate: true", "interface: socketcan, channel: can0"
    )
    moving = real.replace(
        "velocity_model: motor}",
        'velocity_model: motor, limits: {velocity: 900}, startup: ["SERVO ON ON", "START ON ON", "VEL 100 0"]}',
        1,
    )
    said = warnings(parse_config(moving, "real.yaml"))
    assert len(said) == 2
    assert said[0].startswith("real.yaml:5: units[0].startup: unit 'l' moves at start")
    assert said[1].startswith("real.yaml:6: units[1].limits: unit 'r' has no speed limit")
    # a robot's limits count as the unit's; simulated buses are never warned
    limited = real + ONE_PER_DRIVE[len(UNITS) :].replace(
        "    gear_ratio: 10\n",
        "    gear_ratio: 10\n    limits: {linear_mps: 0.5, angular_radps: 1.0}\n",
    )
    assert warnings(parse_config(limited, "real.yaml")) == []
    assert warnings(parse_config(UNITS, "sim.yaml")) == []


def test_the_demos_motion_runs_only_while_simulated() -> None:
    demo = (Path(__file__).parent.parent / "configs" / "demo.yaml").read_text()
    config = parse_config(demo, "demo.yaml")
    assert config.units["left"].startup[-1] == "VEL 300 20"
    real = demo.replace("interface: virtual", "interface: socketcan")
    real = re.sub(r"    simulate:.*?\n\nunits:", "\nunits:", real, flags=re.S)
    config = parse_config(real, "real.yaml")
    assert all(u.startup == () for u in config.units.values())  # the robot waits
    assert warnings(config) == []


def test_robot_limits_beyond_what_the_wire_carries_are_no_limit() -> None:
    real = UNITS.replace(
        "interface: virtual, channel: t, simulate: true", "interface: socketcan, channel: can0"
    )
    fast = real + ONE_PER_DRIVE[len(UNITS) :].replace(
        "    gear_ratio: 10\n",
        "    gear_ratio: 50\n    limits: {linear_mps: 2.0, angular_radps: 4.0}\n",
    )
    said = warnings(parse_config(fast, "real.yaml"))
    assert len(said) == 2 and all("has no speed limit" in w for w in said)


def test_check_points_at_our_keys_and_takes_axis_and_side_in_any_case() -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(ONE_PER_DRIVE.replace("gear_ratio: 10", "gear: 10"), "robot.yaml")
    assert "robots[0].gear: unknown key; did you mean 'gear_ratio'?" in str(info.value)
    assert "radius" not in str(info.value)  # never offered as allowed
    lower = ONE_PER_DRIVE.replace(
        "{unit: l, axis: A, side: left}", "{unit: l, axis: a, side: Left}"
    )
    assert parse_config(lower, "robot.yaml").robots["rover"].wheels[0].axis == 0
    with pytest.raises(ConfigError) as info:
        parse_config(
            ONE_PER_DRIVE.replace(
                "{unit: l, axis: A, side: left}", "{unit: x, axis: C, side: left}"
            ),
            "robot.yaml",
        )
    assert "'C' is not one of: A, B" in str(info.value) and "no unit named 'x'" in str(info.value)
