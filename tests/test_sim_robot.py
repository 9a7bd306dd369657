"""The simulator models the robot: where each wheel physically is, how it is mounted, and
the robot's true motion; the robot wiring faults make the machine differ from the file
while every drive still answers as the file expects. Judged from the drives' motors and
the simulated robot, on a fake clock."""

from __future__ import annotations

import math

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.simulator.robot import SimRobot
from tests.support.rig import Rig, set_twist

# commissioning moves one motor at a time: each drive decided alone (whole_robots=False)
pytestmark = pytest.mark.wire_allow("robot", reason="one wheel at a time, by design")

SKID = """
buses:
  b:
    interface: virtual
    channel: t
    simulate:
      time_constant_ms: 40
      faults: [{faults}]
units:
  - {{name: front, abh3_id: 1, velocity_model: motor}}
  - {{name: rear, abh3_id: 3, protocol: "2023", velocity_model: motor}}
robots:
  - name: rover
    track_m: 0.5
    diameter_m: 0.2
    gear_ratio: 10
    wheels:
      - {{unit: front, axis: A, side: left}}
      - {{unit: front, axis: B, side: right, sign: -1}}
      - {{unit: rear, axis: A, side: left}}
      - {{unit: rear, axis: B, side: right, sign: -1}}
"""
MOTOR = 300.0  # min⁻¹: 0.2 m × π / 10 × 300 / 60 = 0.314 m/s at the wheel


def rig(faults: str = "") -> Rig:
    # one drive at a time, as commissioning moves them: each drive decided alone
    return Rig(parse_config(SKID.format(faults=faults), "skid.yaml"), whole_robots=False)


def turn(r: Rig, unit: str, a: float, b: float, seconds: float = 1.0) -> SimRobot:
    """Motors ``a``, ``b`` of ``unit`` (min⁻¹) for ``seconds``, then stopped; the robot."""
    source = r.own(unit)
    for text in ("SERVO ON ON", "START ON ON", f"VEL {a:g} {b:g}"):
        assert r.sup.apply_text(unit, text, source=source) == ""
    r.run(seconds)
    assert r.sup.apply_text(unit, "VEL 0 0", source=source) == ""
    r.run(0.5)
    return r.sim.robot("rover", r.timeline.now)


def rolled(robot: SimRobot) -> dict[tuple[str, int], float]:
    return {p: round(d, 3) for p, d in robot.travel.items()}


WHEEL_M = 0.2 * math.pi / 10 * MOTOR / 60  # m/s of a wheel at MOTOR


def test_a_healthy_wheel_rolls_its_own_place_forward_as_the_file_says() -> None:
    r = rig()
    robot = turn(r, "front", MOTOR, 0.0)
    travel = rolled(robot)
    assert travel["front", 0] == pytest.approx(WHEEL_M * 1.0, rel=0.06)
    assert [travel[p] for p in (("front", 1), ("rear", 0), ("rear", 1))] == [0, 0, 0]
    # one left wheel of two rolled: the left side at half, the robot turns clockwise
    assert robot.heading < 0 and robot.distance > 0


def test_a_mirrored_motor_rolls_its_wheel_backwards_while_its_encoder_agrees() -> None:
    r = rig("{kind: mirrored_wheel, unit: rear, axis: B}")
    robot = turn(r, "rear", 0.0, -MOTOR)  # sign -1: the file's forward for rear-right
    assert robot.travel["rear", 1] < -0.5 * WHEEL_M
    assert r.drive("rear").sensed(1) == pytest.approx(r.drive("rear").vel[1])  # per-motor: fine


def test_swapped_drives_turn_each_others_wheels() -> None:
    r = rig("{kind: swapped_drives, unit: front, other: rear}")
    robot = turn(r, "front", MOTOR, 0.0)
    assert robot.travel["front", 0] == 0 and robot.travel["rear", 0] > 0.5 * WHEEL_M


def test_a_and_b_swapped_with_their_encoders_turn_the_other_wheel() -> None:
    r = rig("{kind: swapped_axes_with_encoders, unit: front}")
    robot = turn(r, "front", MOTOR, 0.0)
    drive = r.drive("front")
    assert drive.revs[0] > 0 and drive.revs[1] == 0  # motor A turned, its encoder saw it
    assert robot.travel["front", 0] == 0
    assert robot.travel["front", 1] < -0.5 * WHEEL_M  # the right wheel, sign -1: backwards


def test_the_pose_integrates_a_straight_run_and_a_turn_on_the_spot() -> None:
    r = rig("{kind: wrong_track, factor: 1.25}")
    for unit in ("front", "rear"):
        for text in ("SERVO ON ON", "START ON ON"):
            assert r.sup.apply_text(unit, text, source=r.own(unit)) == ""
    source = r.own("front")
    set_twist(r.sup, "rover", 0.3, 0.0, source=source)
    r.run(1.0)
    set_twist(r.sup, "rover", 0.0, 0.0, source=source)
    r.run(0.5)
    robot = r.sim.robot("rover", r.timeline.now)
    assert robot.x == pytest.approx(0.3, rel=0.1) and robot.heading == pytest.approx(0, abs=1e-3)
    x, heading = robot.x, robot.heading
    set_twist(r.sup, "rover", 0.0, 1.0, source=source)  # 1 rad/s by the file's 0.5 m track
    r.run(1.0)
    set_twist(r.sup, "rover", 0.0, 0.0, source=source)
    r.run(0.5)
    robot = r.sim.robot("rover", r.timeline.now)
    assert robot.x == pytest.approx(x, abs=1e-3)  # on the spot
    # the true track is 1.25 × the file's: the same wheel travel turns it 1/1.25 as far
    file_angle = (robot.travel["front", 1] - robot.travel["front", 0]) / 0.5
    assert robot.heading - heading == pytest.approx(file_angle / 1.25, rel=0.05)


def test_a_wrong_protocol_drive_talks_the_other_generation_and_gets_only_the_probe() -> None:
    """The file says 2021 for front: the drive is a 2023 one. The 2021 idle word's B/X data
    select would land on its torque bits; identity before energy: it gets only the probe
    (safe in both layouts), answers in 2023's layout, and is held as the other generation."""
    r = rig("{kind: wrong_protocol, unit: front}")
    drive = r.drive("front")
    assert drive.generation is Generation.G2023
    assert r.sup.apply_text("front", "SERVO ON ON") == ""  # taken before it is recognised
    r.run(0.3)
    assert drive.inputs == flags.ID_PROBE  # nothing else ever reached it
    assert r.sup.units["front"].identified is Generation.G2023
    assert r.sup.units["front"].inputs & flags.LAYOUT_2021.servo.both == 0  # consumed
    reply = frames.decode_dp0_reply(drive._dp0_reply(), Generation.G2021)
    assert isinstance(reply, frames.Dp0Reply2021)
    assert (reply.vel_a, reply.vel_b) == (0.0, 0.0) and (reply.vel_y, reply.vel_x) != (0.0, 0.0)
    assert r.sup.apply_text("front", "SERVO ON ON") == "Invalid Command."  # refused, said
    assert r.drive("rear").generation is Generation.G2023  # the other unit as the file says
    assert r.sup.units["rear"].identified is Generation.G2023


def test_a_file_without_robots_has_a_one_drive_robot_per_unit() -> None:
    r = Rig(
        parse_config(
            """
buses: {b: {interface: virtual, channel: t, simulate: true}}
units:
  - {name: solo, abh3_id: 1, velocity_model: motor, geometry: {wheel: 0.2, width: 0.4}}
""",
            "solo.yaml",
        )
    )
    assert list(r.sim.robots) == ["solo"]
    source = r.own("solo")
    for text in ("SERVO ON ON", "START ON ON", "VEL 100 100"):
        assert r.sup.apply_text("solo", text, source=source) == ""
    r.run(1.0)
    robot = r.sim.robot("solo", r.timeline.now)
    assert robot.travel["solo", 0] > 0 and robot.travel["solo", 1] > 0 and robot.x > 0


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("{kind: swapped_drives, unit: front}", "other: missing: swapped_drives needs it"),
        ("{kind: swapped_drives, unit: front, other: middle}", "no unit 'middle' on bus b"),
        ("{kind: swapped_drives, unit: front, other: front}", "two different units"),
        ("{kind: mirrored_wheel, unit: front}", "axis: missing: mirrored_wheel needs it"),
        ("{kind: wrong_track}", "factor: missing: wrong_track needs it"),
        ("{kind: mirrored_wheel, unit: front, axis: A, other: rear}", "does not apply"),
    ],
)
def test_robot_faults_are_checked_with_file_line(fault: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(SKID.format(faults=fault), "skid.yaml")
    assert "skid.yaml:" in str(err.value) and message in str(err.value)


ONE_WHEEL_AND_A_MONITOR = """
buses:
  b:
    interface: virtual
    channel: t
    simulate:
      faults:
        - {fault}
units:
  - {{name: l, abh3_id: 1, velocity_model: motor}}
  - {{name: r, abh3_id: 3, velocity_model: motor}}
  - {{name: watch, abh3_id: 5, velocity_model: motor, role: monitor}}
robots:
  - name: bot
    track_m: 0.5
    diameter_m: 0.2
    wheels:
      - {{unit: l, axis: A, side: left}}
      - {{unit: r, axis: A, side: right}}
"""


@pytest.mark.parametrize(
    ("fault", "message", "absent"),
    [
        (
            "{kind: wrong_track}",
            "missing: wrong_track needs it (the true track over the file's track_m",
            "pulses",
        ),
        (
            "{kind: wrong_diameter}",
            "missing: wrong_diameter needs it (the true wheel diameter over the file's",
            "pulses",
        ),
        (
            "{kind: mirored_wheel, unit: l, axis: A}",
            "kind: 'mirored_wheel' is not one of: silent,",
            "at_s",  # no false errors of the kind it is not
        ),
        (
            "{kind: mirrored_wheel, unit: l, axis: B}",
            "axis B of unit 'l' is no wheel of robot 'bot' (its wheels on l: axis A)",
            "",
        ),
        (
            "{kind: swapped_drives, unit: l, other: watch}",
            "other: unit 'watch' is a monitor (never commanded, no robot's wheel)",
            "",
        ),
        (
            "{kind: wrong_protocol, unit: watch}",
            "unit: unit 'watch' is a monitor",
            "",
        ),
        (
            "{kind: mirrored_wheel, unit: l, axis: A, at_s: 5}",
            "at_s: does not apply to kind mirrored_wheel: how it is built, for ever",
            "",
        ),
    ],
)
def test_a_robot_fault_that_cannot_be_is_a_file_line_error(
    fault: str, message: str, absent: str
) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(ONE_WHEEL_AND_A_MONITOR.format(fault=fault), "bot.yaml")
    text = str(err.value)
    assert "bot.yaml:8: buses.b.simulate.faults[0]." in text and message in text, text
    assert len(err.value.problems) == 1, text
    if absent:
        assert absent not in text
    if "mirored" in fault:
        assert text.endswith("; did you mean 'mirrored_wheel'?")


def test_a_mirrored_wheel_on_a_wheel_of_the_robot_is_accepted() -> None:
    config = parse_config(
        ONE_WHEEL_AND_A_MONITOR.format(fault="{kind: mirrored_wheel, unit: r, axis: A}"), "bot.yaml"
    )
    assert config.robots["bot"].wheel("r", 0) is not None
