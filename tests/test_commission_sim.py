"""The simulator learns what commissioning must find: a first-order velocity response with
a time constant, and wiring faults (reversed_axis, swapped_axes, scale, no_encoder,
other_velocity_model) — asserted from the drive's own frames and state on a fake clock."""

from __future__ import annotations

import math

import jsonschema
import pytest
import yaml

from abh3_supervisor.clients.schema import config_schema
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.protocol import frames
from tests.support.rig import Rig, present, set_velocity_ab

BASE = """
buses:
  b:
    interface: virtual
    channel: t
    simulate:
{sim}
units:
  - {{name: left, abh3_id: 1, protocol: "{gen}", velocity_model: {model}, command_rate_hz: 50,
     geometry: {{pulses_per_rev: 1000}}, broadcast: {{mask: 0x1f, rate_hz: 50}}}}
  - {{name: right, abh3_id: 3, protocol: "{gen}", velocity_model: {model}, command_rate_hz: 50,
     broadcast: {{mask: 0x1f, rate_hz: 50}}}}
"""


def rig(sim: str, gen: str = "2021", model: str = "motor") -> Rig:
    text = BASE.format(sim=sim, gen=gen, model=model)
    return Rig(parse_config(text, "sim.yaml"))


def moving(r: Rig, unit: str, a: float, b: float, seconds: float) -> None:
    """Switched on, then — once the drive reports it ready (core/readiness.py), so the
    response is timed from the first frame that moves — ``a``, ``b`` for ``seconds``."""
    r.sup.apply_text(unit, "SERVO ON ON")
    r.sup.apply_text(unit, "START ON ON")
    for _ in range(100):
        if r.sup.robot_unready(unit) is None:
            break
        r.run(0.001)
    assert r.sup.robot_unready(unit) is None
    set_velocity_ab(r.sup, unit, a, b, source=present(r.sup, unit))
    r.run(seconds)


def last_reply(r: Rig, unit: str) -> frames.Dp0Reply:
    """The drive's last DP0 reply on the wire, decoded in its generation."""
    drive = r.drive(unit)
    for frame in reversed(r.timeline.frames):
        if frame.arbitration_id & 0xFFFF00FF == 0x00EF0000 | drive.abh3_id:
            reply = frames.decode_dp0_reply(frame.data, drive.generation)
            assert not isinstance(reply, frames.Unknown)
            return reply
    raise AssertionError("no reply")


def test_a_time_constant_gives_a_first_order_response_per_unit() -> None:
    r = rig("      time_constant_ms: 100\n      unit_time_constant_ms: {right: 40}")
    assert r.drive("left").tau == pytest.approx(0.1)
    assert r.drive("right").tau == pytest.approx(0.04)
    for unit in ("left", "right"):
        moving(r, unit, 200, 0, 0.0)
    r.run(0.1)
    start = 0.0  # both commands went out on the first exchange after the call
    left, right = r.drive("left"), r.drive("right")
    # 63 % after one time constant (within the first exchange's delay)
    assert 0.55 * 200 < left.vel[0] < 0.66 * 200
    r.run(0.3 - start)
    assert right.vel[0] == pytest.approx(200, rel=0.01)  # 10 τ
    assert left.vel[0] == pytest.approx(200 * (1 - math.exp(-3.8)), rel=0.03)


def test_without_a_time_constant_the_ramp_at_accel_is_kept() -> None:
    r = rig("      accel: 1000")
    assert r.drive("left").tau is None
    moving(r, "left", 500, 0, 0.2)
    assert 120 < r.drive("left").vel[0] < 200 + 1e-6  # 1000 min⁻¹/s from the first command


@pytest.mark.parametrize("gen", ["2021", "2023"])
@pytest.mark.parametrize("axis", [0, 1])
def test_a_reversed_axis_reports_its_motor_backwards(gen: str, axis: int) -> None:
    name = "AB"[axis]
    r = rig(f"      faults: [{{kind: reversed_axis, unit: left, axis: {name}}}]", gen)
    a, b = (100.0, 0.0) if axis == 0 else (0.0, 100.0)
    moving(r, "left", a, b, 0.5)
    drive = r.drive("left")
    assert drive.vel[axis] == pytest.approx(100)  # it turns as asked ...
    reply = last_reply(r, "left")
    fb = (
        (reply.vel_a, reply.vel_b)
        if isinstance(reply, frames.Dp0Reply2021)
        else (reply.vel_ay, reply.vel_bx)
    )
    assert fb[axis] == pytest.approx(-100)  # ... and says the opposite
    assert drive.pulses[axis] < -10 and drive.pulses[1 - axis] == 0
    state = r.sup.units["left"].feedback
    assert state is not None and (state.vel_a, state.vel_b)[axis] == pytest.approx(-100)


@pytest.mark.parametrize("gen", ["2021", "2023"])
def test_swapped_axes_move_the_other_motor(gen: str) -> None:
    r = rig("      faults: [{kind: swapped_axes, unit: left}]", gen)
    moving(r, "left", 100, 0, 0.5)
    drive = r.drive("left")
    assert drive.vel == pytest.approx([0, 100])
    fb = r.sup.units["left"].feedback
    assert fb is not None and (fb.vel_a, fb.vel_b) == pytest.approx((0, 100))
    assert r.drive("right").vel == [0.0, 0.0]


def test_scale_counts_factor_times_the_pulses_the_geometry_expects() -> None:
    r = rig("      faults: [{kind: scale, unit: left, axis: B, factor: 1.25}]")
    moving(r, "left", 60, 60, 1.0)  # one revolution a second, the ramp done at once
    drive = r.drive("left")
    ratio = drive.pulses[1] / drive.pulses[0]
    assert ratio == pytest.approx(1.25)
    assert drive.pulses[0] == pytest.approx(1000 * (1.0 - 0.02), rel=0.05)  # YAML's 1000/rev
    # the velocity the drive reports is untouched: only the count is off
    fb = r.sup.units["left"].feedback
    assert fb is not None and fb.vel_b == pytest.approx(60)


@pytest.mark.parametrize("gen", ["2021", "2023"])
def test_no_encoder_reports_nothing_while_the_current_rises(gen: str) -> None:
    r = rig("      faults: [{kind: no_encoder, unit: left, axis: A}]", gen)
    moving(r, "left", 100, 0, 0.1)
    early = abs(r.drive("left").current(0))
    r.run(0.4)
    drive = r.drive("left")
    assert drive.pulses[0] == 0 and drive.vel[0] == 0
    assert abs(drive.current(0)) > early > 3.0
    fb = r.sup.units["left"].feedback
    assert fb is not None and fb.vel_a == 0
    brd3 = r.sup.units["left"].status[3][1]
    assert isinstance(brd3, frames.Brd3) and brd3.cur_cmd_ay > 100  # as the bus tells it


@pytest.mark.parametrize("gen", ["2021", "2023"])
def test_other_velocity_model_shows_in_the_control_word(gen: str) -> None:
    r = rig("      faults: [{kind: other_velocity_model, unit: left}]", gen, model="travel")
    r.sup.apply_text("left", "SERVO ON ON")
    r.run(0.5)
    state = r.sup.units["left"]
    assert not state.words["control"] & state.layout.travel_model  # motor, not travel
    right = r.sup.units["right"]
    assert right.words["control"] & right.layout.travel_model


def test_wiring_faults_last_from_the_start_unless_timed() -> None:
    config = parse_config(
        BASE.format(
            sim="      faults: [{kind: reversed_axis, unit: left, axis: B},\n"
            "               {kind: scale, axis: A, factor: 0.5, at_s: 1, for_s: 2}]",
            gen="2021",
            model="motor",
        ),
        "w.yaml",
    )
    sim = config.buses["b"].simulate
    assert sim is not None
    assert sim.faults == (
        Fault(FaultKind.REVERSED_AXIS, 0.0, math.inf, unit="left", axis=1),
        Fault(FaultKind.SCALE, 1.0, 2.0, axis=0, factor=0.5),
    )


@pytest.mark.parametrize(
    ("faults", "message"),
    [
        ("[{kind: reversed_axis, unit: left}]", "faults[0].axis: missing"),
        ("[{kind: scale, axis: A}]", "faults[0].factor: missing"),
        ("[{kind: no_encoder, axis: C}]", "faults[0].axis: 'C' is not one of"),
        ("[{kind: swapped_axes, axis: A}]", "faults[0].axis: does not apply"),
        ("[{kind: silent, at_s: 0, for_s: 1, factor: 2}]", "factor: does not apply"),
    ],
)
def test_bad_wiring_faults_are_named_at_their_line(faults: str, message: str) -> None:
    text = BASE.format(sim=f"      faults: {faults}", gen="2021", model="motor")
    with pytest.raises(ConfigError) as info:
        parse_config(text, "w.yaml")
    assert any(p.startswith("w.yaml:7: ") and message in p for p in info.value.problems), (
        info.value.problems
    )


def test_time_constants_are_checked_at_their_line() -> None:
    sim = "      time_constant_ms: 0\n      unit_time_constant_ms: {middle: 20}"
    with pytest.raises(ConfigError) as info:
        parse_config(BASE.format(sim=sim, gen="2021", model="motor"), "w.yaml")
    problems = "\n".join(info.value.problems)
    assert "w.yaml:7: buses.b.simulate.time_constant_ms: 0 is out of range" in problems
    assert "w.yaml:8: buses.b.simulate.unit_time_constant_ms.middle: no unit 'middle'" in problems


def test_the_schema_knows_the_wiring_faults_and_time_constants() -> None:
    validator = jsonschema.Draft202012Validator(config_schema())
    good = BASE.format(
        sim="      time_constant_ms: 50\n      unit_time_constant_ms: {left: 80}\n"
        "      faults: [{kind: reversed_axis, unit: left, axis: B}, {kind: swapped_axes},"
        " {kind: scale, axis: A, factor: 1.1}, {kind: no_encoder, axis: B}]",
        gen="2023",
        model="motor",
    )
    assert list(validator.iter_errors(yaml.safe_load(good))) == []
    for bad in ("{kind: reversed_axis}", "{kind: scale, axis: A}", "{kind: silent}"):
        data = yaml.safe_load(BASE.format(sim=f"      faults: [{bad}]", gen="2021", model="motor"))
        assert list(validator.iter_errors(data)), bad
