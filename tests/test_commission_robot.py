"""`abh3 commission`'s robot step on a fake clock: for each robot shape (a differential
drive on one drive, one wheel per drive, a skid-steer on two drives) each robot wiring
fault is named with its fix while the healthy wheels pass; a wrong `protocol:` is named at
identity; the wheels' diameter and the track are measured; the operator's keys give the
same verdicts as the simulated robot. What moved is the simulated robot's truth."""

from __future__ import annotations

import argparse
import asyncio
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.commission import LiveBench, TerminalOperator, _summary, _units
from abh3_supervisor.commission.model import Settings, Verdict
from abh3_supervisor.commission.report import Session, html_text, to_json
from abh3_supervisor.commission.robot import RobotResult
from abh3_supervisor.commission.sequence import commission
from abh3_supervisor.commission.unit import RobotView, UnitResult
from abh3_supervisor.commission.wheels import (
    Seen,
    judge_diameter,
    judge_track,
    judge_wheels,
    places,
)
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.robot import RobotConfig
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.simulator.robot import SimRobot
from tests.commission_bench import FakeBench, Headless

# commissioning moves one motor at a time: each drive decided alone (whole_robots=False)
pytestmark = pytest.mark.wire_allow("robot", reason="one wheel at a time, by design")

FAST = Settings(jog_s=0.4, step_s=0.4)
DEMO = Path(__file__).resolve().parent.parent / "configs" / "skid-steer-demo.yaml"
BUS = """
buses:
  b:
    interface: virtual
    channel: c
    simulate:
      time_constant_ms: 40
      faults: [{faults}]
"""
UNIT = (
    '  - {{name: {name}, abh3_id: {id}, protocol: "{gen}", velocity_model: motor, '
    "limits: {{velocity: 3000}}, broadcast: {{mask: 0x1f, rate_hz: 20}}}}\n"
)
SHAPES = {
    # one drive: A the left wheel, B the right one mounted mirrored (sign -1)
    "diff drive on one drive": (
        [("base", 1, "2021")],
        [("base", "A", "left", 1), ("base", "B", "right", -1)],
    ),
    # a drive per wheel, each on its axis A
    "one wheel per drive": (
        [("left", 1, "2021"), ("right", 3, "2023")],
        [("left", "A", "left", 1), ("right", "A", "right", 1)],
    ),
    # four wheels on two drives: front A/B = front-left/front-right, rear the same
    "skid-steer on two drives": (
        [("front", 1, "2023"), ("rear", 3, "2021")],
        [
            ("front", "A", "left", 1),
            ("front", "B", "right", -1),
            ("rear", "A", "left", 1),
            ("rear", "B", "right", -1),
        ],
    ),
}


def config_text(shape: str, faults: str = "") -> str:
    units, wheels = SHAPES[shape]
    text = BUS.format(faults=faults) + "units:\n"
    text += "".join(UNIT.format(name=n, id=i, gen=g) for n, i, g in units)
    text += "robots:\n  - name: robot\n    track_m: 0.5\n    diameter_m: 0.15\n"
    text += "    gear_ratio: 10\n    pulses_per_rev: 4096\n    wheels:\n"
    for unit, axis, side, sign in wheels:
        text += f"      - {{unit: {unit}, axis: {axis}, side: {side}, sign: {sign}}}\n"
    return text


def bench_of(shape: str, faults: str = "") -> FakeBench:
    return FakeBench(parse_config(config_text(shape, faults), "robot.yaml"))


def run(
    bench: FakeBench, operator: object | None = None
) -> tuple[dict[str, UnitResult], dict[str, RobotResult], str | None]:
    op = operator or Headless(bench)
    results: dict[str, UnitResult] = {}
    robots: dict[str, RobotResult] = {}
    units = list(bench.config.units)
    why = asyncio.run(
        commission(bench, op, units, FAST, results, None, robots)  # type: ignore[arg-type]
    )
    bench.run(0.5)
    return results, robots, why


def failing(result: RobotResult) -> list[tuple[str, str]]:
    return [(c.name, c.fix) for c in result.checks if c.verdict is Verdict.FAIL]


def passed_wheels(result: RobotResult) -> list[str]:
    return [
        c.name
        for c in result.checks
        if c.verdict is Verdict.PASS
        and c.name.startswith("wheel ")
        and "(" in c.name
        and "diameter" not in c.name
    ]


def assert_at_rest(bench: FakeBench) -> None:
    for unit in bench.config.units:
        drive = bench.drive(unit)
        assert drive.vel == pytest.approx([0.0, 0.0], abs=0.5)
        assert not drive.inputs & (drive.layout.servo.both | drive.layout.start.both)


# ---------------------------------------------------------------- healthy robots


@pytest.mark.parametrize("shape", list(SHAPES))
def test_a_healthy_robot_passes_every_wheel_its_diameter_and_its_track(shape: str) -> None:
    bench = bench_of(shape)
    results, robots, why = run(bench)
    assert why is None
    assert all(r.verdict is Verdict.PASS for r in results.values()), results
    robot = robots["robot"]
    assert robot.verdict is Verdict.PASS, robot.checks
    assert len(passed_wheels(robot)) == len(bench.config.robots["robot"].wheels)
    names = [c.name for c in robot.checks]
    assert "wheel diameter (straight run)" in names and "track (turn on the spot)" in names
    truth = bench.sim.robot("robot", bench.now())
    assert truth.distance > 0.1  # it did run and turn
    assert_at_rest(bench)


def test_each_wheel_turns_alone_within_its_jog_speed() -> None:
    """From the simulated robot: in the per-wheel part every wheel rolled forward once, and
    no motor ever turned faster than its unit's jog speed."""
    bench = bench_of("skid-steer on two drives")
    fastest = 0.0

    class Watch:
        def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
            pass

        def poll(self, now: float) -> list[tuple[int, bytes]]:
            nonlocal fastest
            fastest = max([fastest, *(abs(v) for d in bench.sim.drives.values() for v in d.vel)])
            return []

        def next_deadline(self) -> float:
            return bench.now() + 0.01

        def on_send_failed(self, arbitration_id: int) -> None:
            pass

        def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
            pass

    bench.timeline.add(Watch())
    _, robots, _ = run(bench)
    seen = robots["robot"].seen
    assert all(s.place == place and s.direction == 1 for place, s in seen.items())
    assert fastest <= FAST.jog_speed(3000) * 1.05


# ---------------------------------------------------------------- robot wiring faults

FAULTS = {
    "mirrored_wheel": (
        "{kind: mirrored_wheel, unit: %(u)s, axis: A}",
        "mirrored wheel %(u)s.A",
        "sign: -1 for robots.robot.wheels",
    ),
    "swapped_drives": (
        "{kind: swapped_drives, unit: %(v)s, other: %(u)s}",  # named in the robot's order
        "drives swapped: %(u)s ↔ %(v)s",
        "swap unit: %(u)s and unit: %(v)s",
    ),
    "swapped_axes_with_encoders": (
        "{kind: swapped_axes_with_encoders, unit: %(u)s}",
        "A and B swapped with their encoders: %(u)s",
        "swap axis: A and axis: B of unit %(u)s's wheels",
    ),
}
CASES = [
    (shape, fault)
    for shape in SHAPES
    for fault in FAULTS
    # one drive cannot be swapped with another; a drive with one wheel has no B wheel
    if not (shape == "diff drive on one drive" and fault == "swapped_drives")
    and not (shape == "one wheel per drive" and fault == "swapped_axes_with_encoders")
]


@pytest.mark.parametrize(("shape", "fault"), CASES)
def test_each_robot_fault_is_named_with_its_fix_and_the_healthy_wheels_pass(
    shape: str, fault: str
) -> None:
    units = [u for u, _, _ in SHAPES[shape][0]]
    names = {"u": units[-1], "v": units[0]}
    if fault == "swapped_drives":
        names = {"u": units[0], "v": units[-1]}
    yaml, name, fix = (text % names for text in FAULTS[fault])
    bench = bench_of(shape, yaml)
    results, robots, why = run(bench)
    assert why is None
    # every drive passes its own steps: the fault is the robot's
    assert all(r.verdict is Verdict.PASS for r in results.values()), {
        u: [c for c in r.checks if c.verdict is not Verdict.PASS] for u, r in results.items()
    }
    robot = robots["robot"]
    fails = failing(robot)
    assert len(fails) == 1 and fails[0][0].startswith(name), robot.checks
    assert fix in fails[0][1]
    touched = {units[-1], units[0]} if fault == "swapped_drives" else {units[-1]}
    if fault == "mirrored_wheel":
        touched = {f"{units[-1]}.A"}
    healthy = [w for w in bench.config.robots["robot"].wheels if w.unit not in touched]
    healthy = [w for w in healthy if w.name not in touched]
    assert {f"wheel {w.name}" for w in healthy} <= {n.split(" (")[0] for n in passed_wheels(robot)}
    # the straight run waits for the wiring: nothing drove the whole robot
    assert any(c.verdict is Verdict.SKIPPED for c in robot.checks)
    assert_at_rest(bench)


def test_a_and_b_swapped_on_a_drive_with_one_wheel_is_named_from_the_drives_own_feedback() -> None:
    """Wheels on left.A and right.A; left's A and B swapped with their encoders: motor A
    turns nothing (B is no wheel), yet its drive reports it turning — the axis swap."""
    bench = bench_of("one wheel per drive", "{kind: swapped_axes_with_encoders, unit: left}")
    results, robots, _ = run(bench)
    assert all(r.verdict is Verdict.PASS for r in results.values())
    robot = robots["robot"]
    fails = failing(robot)
    assert [n for n, _ in fails] == [
        "A and B swapped with their encoders: left (wheel left.A (left) did not turn)"
    ]
    assert "axis: B for robots.robot.wheels[0] (left axis A)" in fails[0][1]
    assert "encoder cables" in fails[0][1] and "coupled" in fails[0][1]
    seen = robot.seen["left", 0]
    assert seen.place is None and seen.motor_min == pytest.approx(FAST.jog_speed(3000), rel=0.1)
    assert "wheel right.A (right)" in passed_wheels(robot)


@pytest.mark.parametrize(
    ("fault", "name", "fix"),
    [
        ("{kind: wrong_track, factor: 1.3}", "track off by +30%", "track_m: 0.65 in robots: robot"),
        (
            "{kind: wrong_diameter, factor: 0.5}",
            "wheel diameter off by -50%",
            "diameter_m: 0.075 in robots: robot",
        ),
    ],
)
@pytest.mark.parametrize("shape", list(SHAPES))
def test_a_wrong_track_or_diameter_is_measured_with_its_fix(
    shape: str, fault: str, name: str, fix: str
) -> None:
    bench = bench_of(shape, fault)
    _, robots, _ = run(bench)
    fails = failing(robots["robot"])
    assert [n for n, _ in fails] == [name]
    assert fix in fails[0][1]


def test_a_wrong_diameter_on_one_side_is_named_by_the_straight_runs_curve() -> None:
    """The right drive's wheels are 0.8 × the file's: the straight run curves; the side
    and its unit are named, with a diameter_m per wheel of it (not a robot-wide mean),
    and the track still passes (the turn corrected by each side's ratio)."""
    text = (
        BUS.format(faults="{kind: wrong_diameter, unit: rp, factor: 0.8}")
        + "units:\n"
        + UNIT.format(name="lp", id=1, gen="2021")
        + UNIT.format(name="rp", id=3, gen="2023")
        + "robots:\n  - name: robot\n    track_m: 0.5\n    diameter_m: 0.15\n"
        + "    gear_ratio: 10\n    wheels:\n"
        + "      - {unit: lp, axis: A, side: left}\n      - {unit: lp, axis: B, side: left}\n"
        + "      - {unit: rp, axis: A, side: right}\n      - {unit: rp, axis: B, side: right}\n"
    )
    bench = FakeBench(parse_config(text, "sides.yaml"))
    _, robots, _ = run(bench)
    robot = robots["robot"]
    fails = failing(robot)
    assert [n for n, _ in fails] == ["wheel diameter off: right side (rp) -20%"], robot.checks
    check = next(c for c in robot.checks if c.verdict is Verdict.FAIL)
    assert "the straight run curved -" in check.measured
    assert "diameter_m: 0.12 for robots.robot.wheels[2] (rp axis A)" in check.fix
    assert "diameter_m: 0.12 for robots.robot.wheels[3] (rp axis B)" in check.fix
    assert "wheels[0]" not in check.fix and "in robots: robot" not in check.fix
    track = next(c for c in robot.checks if c.name.startswith("track"))
    assert track.verdict is Verdict.PASS


LEGACY = BUS + (
    "units:\n"
    "  - {{name: front, abh3_id: 1, velocity_model: motor, limits: {{velocity: 3000}},\n"
    "     geometry: {{rate_num: 1, rate_den: 10, wheel: 0.15, width: 0.5, pulses_per_rev: 4096}}}}\n"
    '  - {{name: rear, abh3_id: 3, protocol: "2023", velocity_model: motor,\n'
    "     limits: {{velocity: 3000}},\n"
    "     geometry: {{rate_num: 1, rate_den: 10, wheel: 0.15, width: 0.5, pulses_per_rev: 4096}}}}\n"
)


@pytest.mark.parametrize(
    ("fault", "robot", "name", "fix"),
    [
        (
            "{kind: mirrored_wheel, unit: rear, axis: B}",
            "rear",
            "mirrored wheel rear.B (right)",
            "robots: section with sign: -1 for unit rear axis B",
        ),
        (
            "{kind: swapped_axes_with_encoders, unit: front}",
            "front",
            "A and B swapped with their encoders: front",
            "axis A on the right and B on the left",
        ),
        (
            "{kind: swapped_drives, unit: rear, other: front}",
            "front",
            "drives swapped: front ↔ rear",
            "swap the abh3_id of units front and rear",
        ),
        (
            "{kind: wrong_diameter, unit: rear, factor: 2}",
            "rear",
            "wheel diameter off by +100%",
            "units.rear.geometry.wheel: 0.3",
        ),
    ],
)
def test_a_file_without_robots_commissions_each_units_one_drive_robot(
    fault: str, robot: str, name: str, fix: str
) -> None:
    """The legacy file: each unit a robot of its own from its geometry (A left, B right)."""
    bench = FakeBench(parse_config(LEGACY.format(faults=fault), "legacy.yaml"))
    results, robots, _ = run(bench)
    assert all(r.verdict is Verdict.PASS for r in results.values())
    fails = failing(robots[robot])
    assert [n for n, _ in fails] == [name] and fix in fails[0][1]
    if "swapped_drives" not in fault:
        other = "front" if robot == "rear" else "rear"
        assert robots[other].verdict is Verdict.PASS


TWO_ROBOTS = BUS + (
    "units:\n"
    "  - {{name: a, abh3_id: 1, velocity_model: motor, limits: {{velocity: 3000}}}}\n"
    '  - {{name: b, abh3_id: 3, protocol: "2023", velocity_model: motor,\n'
    "     limits: {{velocity: 3000}}}}\n"
    "robots:\n"
    "  - name: one\n    track_m: 0.5\n    diameter_m: 0.15\n    gear_ratio: 10\n"
    "    wheels: [{{unit: a, axis: A, side: left}}, {{unit: a, axis: B, side: right}}]\n"
    "  - name: two\n    track_m: 0.5\n    diameter_m: 0.15\n    gear_ratio: 10\n"
    "    wheels: [{{unit: b, axis: A, side: left}}, {{unit: b, axis: B, side: right}}]\n"
)


@pytest.mark.parametrize(
    ("text", "robot", "other", "fixes"),
    [
        (
            LEGACY.format(faults="{kind: swapped_drives, unit: front, other: rear}"),
            "front",
            "rear",
            ["swap the abh3_id of units front and rear"],
        ),
        (
            TWO_ROBOTS.format(faults="{kind: swapped_drives, unit: a, other: b}"),
            "one",
            "two",
            [
                "swap the abh3_id of units a and b",
                "unit: a → b in robots.one.wheels and unit: b → a in robots.two.wheels",
            ],
        ),
    ],
)
def test_drives_swapped_between_two_robots_are_reported_with_a_fix_check_accepts(
    text: str, robot: str, other: str, fixes: list[str]
) -> None:
    """Each drive turned the other robot's wheels: the report is written (the robot's
    page names the other robot's wheel) and the fix never puts one unit in two robots."""
    bench = FakeBench(parse_config(text, "two.yaml"))
    results, robots, _ = run(bench)
    fails = failing(robots[robot])
    assert len(fails) == 1 and fails[0][0].startswith("drives swapped"), fails
    for fix in fixes:
        assert fix in fails[0][1]
    assert "swap unit: " not in fails[0][1]  # within one robot's wheels: check refuses it
    session = Session("t", "now", "two.yaml", "", FAST, results, robots=robots)
    wheels = {w["place"]: w["turned"] for w in to_json(session)["robots"][robot]["wheels"]}
    assert wheels == {
        "left": f"left of robot {other}, forward",
        "right": f"right of robot {other}, forward",
    }
    assert f"left of robot {other}, forward" in html_text(session)


def test_the_per_motor_scale_is_held_against_the_robots_wheels_pulses_per_rev() -> None:
    """Both motors of a drive count 1.2 × (so A = B): the wheels' pulses_per_rev (the
    robot's, 4096) catches it, and the advice names the robot's keys, not geometry."""
    faults = "{kind: scale, unit: rear, axis: A, factor: 1.2}, "
    faults += "{kind: scale, unit: rear, axis: B, factor: 1.2}"
    results, robots, _ = run(bench_of("skid-steer on two drives", faults))
    assert results["front"].verdict is Verdict.PASS
    fails = [c for c in results["rear"].checks if c.verdict is Verdict.FAIL]
    assert [c.name for c in fails] == [
        "gear/geometry scale of motor A off by +20%",
        "gear/geometry scale of motor B off by +20%",
    ]
    assert fails[0].limit == "4096 ±5% pulses/rev"
    assert (
        "pulses_per_rev: 49" in fails[0].fix
        and "for robots.robot.wheels[2] (rear.A)" in fails[0].fix
    )
    assert "robots.robot.pulses_per_rev for every wheel" in fails[0].fix
    assert "geometry" not in fails[0].fix
    assert robots["robot"].checks[0].verdict is Verdict.SKIPPED


def test_drives_swapped_and_a_mirrored_wheel_are_both_named() -> None:
    faults = "{kind: swapped_drives, unit: front, other: rear}, "
    faults += "{kind: mirrored_wheel, unit: rear, axis: B}"
    _, robots, _ = run(bench_of("skid-steer on two drives", faults))
    fails = failing(robots["robot"])
    assert [n for n, _ in fails] == [
        "drives swapped: front ↔ rear",
        "mirrored wheel at front-right (besides the swap)",
    ]
    assert "a fault behind the swap shows once it is fixed" in fails[0][1]


def test_drives_swapped_between_sides_mounted_opposite_is_the_swap_alone() -> None:
    """Left wheels sign 1, right ones -1 (mirror-mounted): a left drive on the right
    wheels rolls them backwards by their mounting, not as a mirrored wheel."""
    text = (
        BUS.format(faults="{kind: swapped_drives, unit: lp, other: rp}")
        + "units:\n"
        + UNIT.format(name="lp", id=1, gen="2021")
        + UNIT.format(name="rp", id=3, gen="2023")
        + "robots:\n  - name: robot\n    track_m: 0.5\n    diameter_m: 0.15\n"
        + "    gear_ratio: 10\n    wheels:\n"
        + "      - {unit: lp, axis: A, side: left}\n      - {unit: lp, axis: B, side: left}\n"
        + "      - {unit: rp, axis: A, side: right, sign: -1}\n"
        + "      - {unit: rp, axis: B, side: right, sign: -1}\n"
    )
    _, robots, _ = run(FakeBench(parse_config(text, "sides.yaml")))
    assert [n for n, _ in failing(robots["robot"])] == ["drives swapped: lp ↔ rp"]


def test_drives_swapped_on_a_robot_with_unequal_sides_is_one_fault() -> None:
    """Two left wheels on l (A, B), one right wheel on r.A: swapped, l's B turns nothing
    (r has no B wheel) — still the drives swapped, not three wheels' faults."""
    text = (
        BUS.format(faults="{kind: swapped_drives, unit: l, other: r}")
        + "units:\n"
        + UNIT.format(name="l", id=1, gen="2021")
        + UNIT.format(name="r", id=3, gen="2023")
        + "robots:\n  - name: robot\n    track_m: 0.5\n    diameter_m: 0.15\n"
        + "    gear_ratio: 10\n    wheels:\n"
        + "      - {unit: l, axis: A, side: left}\n      - {unit: l, axis: B, side: left}\n"
        + "      - {unit: r, axis: A, side: right}\n"
    )
    _, robots, _ = run(FakeBench(parse_config(text, "unequal.yaml")))
    robot = robots["robot"]
    assert [c.name for c in robot.checks if c.verdict is Verdict.FAIL] == ["drives swapped: l ↔ r"]
    check = robot.checks[0]
    assert (
        "l.A turned right" in check.measured
        and "l.B turned none (r has no wheel on axis B)" in (check.measured)
    )
    assert "r.A turned front-left" in check.measured


# ---------------------------------------------------------------- protocol generation


@pytest.mark.parametrize("shape", list(SHAPES))
def test_a_wrong_protocol_is_named_at_identity_and_nothing_of_that_drive_moves(
    shape: str,
) -> None:
    units = SHAPES[shape][0]
    unit, _, gen = units[-1]
    other = "2023" if gen == "2021" else "2021"
    bench = bench_of(shape, f"{{kind: wrong_protocol, unit: {unit}}}")
    results, robots, _ = run(bench)
    check = next(c for c in results[unit].checks if c.name == "protocol generation")
    assert check.step == "identity" and check.verdict is Verdict.FAIL
    assert f'protocol: "{other}" for units.{unit}' in check.fix
    assert f"{other}'s layout" in check.measured
    assert bench.drive(unit).revs == [0.0, 0.0]  # refused before any motion
    for name, _, _ in units[:-1]:
        assert results[name].verdict is Verdict.PASS
    # the robot step needs every drive of the robot: not run, and said so
    assert robots["robot"].checks[0].verdict is Verdict.SKIPPED
    assert robots["robot"].verdict is Verdict.SKIPPED  # "not run", not a warning
    assert robots["robot"].ended == f"not run: unit {unit} did not pass its own steps"


def test_a_robot_with_a_unit_not_commissioned_is_not_run_and_says_which() -> None:
    bench = bench_of("skid-steer on two drives")
    results: dict[str, UnitResult] = {}
    robots: dict[str, RobotResult] = {}
    said: list[str] = []
    op = Headless(bench)
    op.say = said.append  # type: ignore[method-assign,assignment]
    asyncio.run(commission(bench, op, ["front"], FAST, results, None, robots))
    robot = robots["robot"]
    assert robot.verdict is Verdict.SKIPPED and robot.ended == "not run: rear not commissioned"
    assert "robot robot: not run: rear not commissioned" in said
    assert bench.drive("rear").revs == [0.0, 0.0]


def test_a_robots_name_stands_for_its_units_and_an_unknown_name_lists_the_robots() -> None:
    config = parse_config(config_text("skid-steer on two drives"), "robot.yaml")
    assert _units(config, ["robot"]) == ["front", "rear"]
    assert _units(config, ["rear", "robot"]) == ["rear", "front"]
    with pytest.raises(ConfigError) as err:
        _units(config, ["rover"])
    assert "no unit or robot named 'rover' (units: front, rear; robots: robot)" in str(err.value)


def test_the_summary_puts_why_the_rest_was_not_run_after_the_wheel_that_failed(
    capsys: pytest.CaptureFixture[str],
) -> None:
    bench = bench_of("skid-steer on two drives", "{kind: mirrored_wheel, unit: rear, axis: B}")
    results, robots, _ = run(bench)
    _summary(Session("t", "now", "robot.yaml", "", FAST, results, robots=robots))
    out = capsys.readouterr().out
    assert out.index("mirrored wheel rear.B") < out.index("fix the wheels above first")


# ---------------------------------------------------------------- the operator's keys


class Terminal:
    """A person at the terminal, through :class:`TerminalOperator`'s key handling: each
    answer is typed as keys, read off the simulated robot (what the person would see)."""

    def __init__(self, bench: FakeBench, digits: bool = True) -> None:
        self.bench, self.digits = bench, digits
        consent = argparse.Namespace(wheels_off_ground=True, yes=True)
        self.term = TerminalOperator(cast(LiveBench, self), consent, keys=True)
        self.interactive = True
        self.truth: SimRobot = bench.sim.robots["robot"]
        self.mark = self._now()
        self.typed: list[str] = []
        self.place: tuple[str, int] | None = None

    def _now(self) -> tuple[dict[tuple[str, int], float], float, float]:
        return dict(self.truth.travel), self.truth.distance, self.truth.heading

    def estop(self) -> float:  # the key's bench, as LiveBench's
        self.bench.sup.emergency_stop("commission")
        return self.bench.now()

    def say(self, text: str) -> None:
        pass

    async def confirm(self, question: str) -> bool:
        self.mark = self._now()
        return await self.term.confirm(question)

    async def press_estop(self, prompt: str) -> float | None:
        job = asyncio.ensure_future(self.term.press_estop(prompt))
        await asyncio.sleep(0)
        self.term.key("e")
        return await job

    async def _keys(self, keys: str) -> None:
        await asyncio.sleep(0)
        for key in keys:
            self.typed.append(key)
            self.term.key(key)
        await asyncio.sleep(0)

    async def choose(self, question: str, options: Sequence[tuple[str, str]]) -> str | None:
        job = asyncio.ensure_future(self.term.choose(question, options))
        key = "x" + self.answer(question, options)  # x: not an option, ignored
        await self._keys(key)
        return await job

    def answer(self, question: str, options: Sequence[tuple[str, str]]) -> str:
        before = self.mark[0]
        moved = {p: self.truth.travel[p] - before[p] for p in before}
        if "which wheel" in question:
            self.place = max(moved, key=lambda p: abs(moved[p]))
            if abs(moved[self.place]) < 0.01:
                return "0"
            name = places(self.bench.config.robots["robot"])[self.place]
            return next(k for k, meaning in options if meaning == name)
        assert self.place is not None
        way = "f" if moved[self.place] > 0 else "b"
        self.mark = self._now()
        return way.upper()  # keys are taken in either case

    async def measure(self, question: str) -> float | None:
        job = asyncio.ensure_future(self.term.measure(question))
        _, distance, heading = self.mark
        if not self.digits:
            text = "\r"
        elif "how far did it go" in question:
            text = f"{self.truth.distance - distance:.3f}\r"
        else:
            text = f"{math.degrees(self.truth.heading - heading):.1f}\r"
        await self._keys("9\x7f" + text)  # a slip, taken back with backspace
        self.mark = self._now()
        return await job


class Asking(FakeBench):
    """No simulated robot to ask: the operator tells."""

    def sim_robot(self, name: str) -> RobotView | None:
        return None


def asking(shape: str, faults: str = "") -> Asking:
    return Asking(parse_config(config_text(shape, faults), "robot.yaml"))


@pytest.mark.parametrize(
    ("faults", "name"),
    [
        ("", None),
        ("{kind: mirrored_wheel, unit: rear, axis: B}", "mirrored wheel rear.B (rear-right)"),
        ("{kind: swapped_drives, unit: front, other: rear}", "drives swapped: front ↔ rear"),
        ("{kind: wrong_track, factor: 0.8}", "track off by -20%"),
    ],
)
def test_the_operators_keys_give_the_same_verdicts(faults: str, name: str | None) -> None:
    bench = asking("skid-steer on two drives", faults)
    operator = Terminal(bench)
    _, robots, why = run(bench, operator)
    assert why is None
    robot = robots["robot"]
    assert robot.source == "the operator"
    assert [n for n, _ in failing(robot)] == ([name] if name else [])
    if name is None:
        assert robot.verdict is Verdict.PASS
    assert "F" in operator.typed  # keys, not a shortcut
    if name is None or "track" in name:  # measured, typed in
        assert "\r" in operator.typed


def test_enter_at_a_measurement_skips_it_and_the_report_says_so() -> None:
    bench = asking("one wheel per drive")
    _, robots, _ = run(bench, Terminal(bench, digits=False))
    robot = robots["robot"]
    skipped = {c.name: c.measured for c in robot.checks if c.verdict is Verdict.SKIPPED}
    assert skipped == {
        "wheel diameter (straight run)": "not measured: the operator skipped it",
        "track (turn on the spot)": "not measured: the operator skipped it",
    }
    assert robot.verdict is Verdict.WARN  # the wheels passed; the geometry is unchecked


def test_the_e_stop_key_at_a_wheel_question_ends_the_session_with_everything_stopped() -> None:
    bench = asking("diff drive on one drive")

    class Stopping(Terminal):
        def answer(self, question: str, options: Sequence[tuple[str, str]]) -> str:
            return "e"

    results, robots, why = run(bench, Stopping(bench))
    assert why == "e-stop pressed"
    assert failing(robots["robot"]) == [("aborted", "")]
    assert robots["robot"].checks[-1].measured == "e-stop pressed during its step"
    assert results["base"].verdict is Verdict.PASS  # its own steps were over and passed
    assert_at_rest(bench)


def test_without_a_terminal_or_a_simulated_robot_the_robot_step_is_not_run() -> None:
    bench = asking("diff drive on one drive")
    _, robots, _ = run(bench)
    robot = robots["robot"]
    assert [c.verdict for c in robot.checks] == [Verdict.SKIPPED]
    assert "no terminal" in robot.checks[0].measured
    assert robot.verdict is Verdict.WARN


# ---------------------------------------------------------------- the report


def test_the_report_has_the_robots_page() -> None:
    bench = bench_of("skid-steer on two drives", "{kind: mirrored_wheel, unit: rear, axis: B}")
    results, robots, _ = run(bench)
    session = Session("t", "now", "robot.yaml", "", FAST, results, robots=robots)
    doc = to_json(session)
    assert doc["verdict"] == "fail"
    wheels = {w["place"]: w["turned"] for w in doc["robots"]["robot"]["wheels"]}
    assert wheels == {
        "front-left": "front-left, forward",
        "front-right": "front-right, forward",
        "rear-left": "rear-left, forward",
        "rear-right": "rear-right, backward",
    }
    html = html_text(session)
    assert '<h2 id="robot-robot">Robot robot — fail</h2>' in html
    assert "mirrored wheel rear.B (rear-right)" in html and "sign: 1 for robots.robot" in html


# ---------------------------------------------------------------- the shipped demo


@pytest.mark.wallclock
def test_the_skid_steer_demo_names_its_mirrored_wheel_with_exit_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "run.html"
    argv = ["commission", str(DEMO), "--wheels-off-ground", "--yes", "--report", str(report)]
    assert main([*argv, "--jog-seconds", "0.3", "--step-seconds", "0.3"]) == 1
    out = capsys.readouterr().out
    assert "  front: PASS\n  rear: PASS\n  robot rover: FAIL\n" in out
    assert "mirrored wheel rear.B (rear-right)" in out
    assert "fix: sign: -1 for robots.rover.wheels[3]" in out
    doc = json.loads(report.with_suffix(".json").read_text())
    turned = [w["turned"] for w in doc["robots"]["rover"]["wheels"]]
    assert turned == [
        "front-left, forward",
        "front-right, forward",
        "rear-left, forward",
        "rear-right, backward",
    ]


# ---------------------------------------------------------------- the judgements alone


def _robot(shape: str) -> RobotConfig:
    return parse_config(config_text(shape), "robot.yaml").robots["robot"]


def test_places_are_named_by_side_and_front_to_rear_as_listed() -> None:
    assert list(places(_robot("skid-steer on two drives")).values()) == [
        "front-left",
        "rear-left",
        "front-right",
        "rear-right",
    ]
    assert list(places(_robot("one wheel per drive")).values()) == ["left", "right"]


def test_a_wheel_that_did_not_turn_or_turned_another_is_named_with_its_keys() -> None:
    robot = _robot("skid-steer on two drives")
    seen = {(w.unit, w.axis): Seen((w.unit, w.axis), 1) for w in robot.wheels}
    seen["front", 0] = Seen(None, 0)
    seen["rear", 1] = Seen(("front", 1), 1)  # and front.B turned its own: not a swap
    checks = {c.name: c for c in judge_wheels(robot, seen)}
    assert checks["wheel front.A (front-left) did not turn"].verdict is Verdict.FAIL
    other = checks["wheel rear.B (rear-right) turned another wheel"]
    assert other.measured == "front-right turned"
    assert "unit: and axis: of the front-right wheel" in other.fix
    assert checks["wheel rear.A (rear-left)"].verdict is Verdict.PASS


def test_a_still_wheel_whose_motor_turned_and_whose_twin_is_no_wheel_is_an_axis_swap() -> None:
    robot = _robot("one wheel per drive")
    seen = {(w.unit, w.axis): Seen((w.unit, w.axis), 1) for w in robot.wheels}
    seen["right", 0] = Seen(None, 0)  # nobody watched the drive: a still wheel
    assert [c.name for c in judge_wheels(robot, seen) if c.verdict is Verdict.FAIL] == [
        "wheel right.A (right) did not turn"
    ]
    seen["right", 0] = Seen(None, 0, motor_min=150.0)
    (check,) = [c for c in judge_wheels(robot, seen) if c.verdict is Verdict.FAIL]
    assert check.name.startswith("A and B swapped with their encoders: right")
    assert "reports motor A turning (+150 min⁻¹)" in check.measured
    # on a drive whose other axis is a wheel too, a still wheel with its motor turning is
    # not the swap (the twin would have turned): a wheel not coupled
    skid = _robot("skid-steer on two drives")
    seen = {(w.unit, w.axis): Seen((w.unit, w.axis), 1) for w in skid.wheels}
    seen["rear", 0] = Seen(None, 0, motor_min=150.0)
    (check,) = [c for c in judge_wheels(skid, seen) if c.verdict is Verdict.FAIL]
    assert check.name == "wheel rear.A (rear-left) did not turn"
    assert "although drive rear reports motor A turning" in check.measured


def test_a_straight_run_off_by_a_factor_names_the_diameter_it_measured() -> None:
    robot = _robot("diff drive on one drive")  # diameter_m: 0.15
    check = judge_diameter(robot, expected_m=0.4, measured_m=0.2)
    assert check.verdict is Verdict.FAIL and "diameter_m: 0.075" in check.fix
    radius = judge_diameter(robot, expected_m=0.4, measured_m=0.8)  # the file gave a radius
    assert radius.name == "wheel diameter off by +100%" and "diameter_m: 0.3 " in radius.fix
    assert "not a radius" in radius.fix
    assert judge_diameter(robot, 0.4, 0.41).verdict is Verdict.PASS
    assert judge_track(robot, math.pi / 2, math.pi / 2 * 1.02).verdict is Verdict.PASS
    wide = judge_track(robot, math.pi / 2, math.pi / 4)  # turned half as far: twice the track
    assert wide.verdict is Verdict.FAIL and "track_m: 1" in wide.fix
