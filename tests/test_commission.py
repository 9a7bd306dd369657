"""`abh3 commission` on a fake clock: every wiring fault on either generation is named with
its fix and the right drive passes; what the drives were commanded and where they ended
is read from the frames on the wire and the simulator, not from the tool's own words."""

from __future__ import annotations

import asyncio
import math
import re
from html.parser import HTMLParser

import pytest

from abh3_supervisor.commission import analysis
from abh3_supervisor.commission.model import Settings, SettingsError, Trace, Verdict
from abh3_supervisor.commission.report import Session, html_text, json_text, to_json
from abh3_supervisor.commission.sequence import commission
from abh3_supervisor.commission.svg import LEFT, PANEL, RIGHT, WIDTH
from abh3_supervisor.commission.unit import UnitResult
from abh3_supervisor.config import load_config, parse_config
from abh3_supervisor.core.kinematics import yx_to_ab
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.frames import Generation
from tests.commission_bench import FakeBench, Headless
from tests.support.rig import present, set_velocity_ab
from tests.support.safe_word import is_safe_word

ROBOT = """
buses:
  robot:
    interface: virtual
    channel: c
    simulate:
      time_constant_ms: {tau}
      faults: [{faults}]
units:
  - {{name: u1, abh3_id: 1, protocol: "{gen}", velocity_model: {model}, limits: {{velocity: 2000}},
     geometry: {{pulses_per_rev: 1024}}, broadcast: {{mask: 0x1f, rate_hz: 20}}}}
  - {{name: u2, abh3_id: 3, host_id: 9, protocol: "{gen}", velocity_model: {model},
     limits: {{velocity: 2000}}, geometry: {{pulses_per_rev: 1024}},
     broadcast: {{mask: 0x1f, rate_hz: 20}}}}
"""
FAST = Settings(jog_s=0.5, step_s=0.5)


def robot(faults: str = "", gen: str = "2021", model: str = "motor", tau: int = 50) -> FakeBench:
    text = ROBOT.format(faults=faults, gen=gen, model=model, tau=tau)
    return FakeBench(parse_config(text, "robot.yaml"))


def session(
    bench: FakeBench, settings: Settings = FAST, units: list[str] | None = None
) -> tuple[dict[str, UnitResult], str | None, Headless]:
    operator = Headless(bench)
    results: dict[str, UnitResult] = {}
    names = units or list(bench.config.units)
    why = asyncio.run(commission(bench, operator, names, settings, results))
    bench.run(0.5)  # the stop, answered
    return results, why, operator


def failed(result: UnitResult) -> list[str]:
    return [c.name for c in result.checks if c.verdict is Verdict.FAIL]


def commands(bench: FakeBench, unit: str) -> list[tuple[float, float, float, int]]:
    """(t, A, B, inputs) of every DP0 command to ``unit``'s drive on the wire."""
    cfg = bench.config.units[unit]
    wanted = ids.dp0_command_id(cfg.abh3_id, cfg.host_id)
    out = []
    for f in bench.timeline.frames:
        if f.arbitration_id == wanted:
            cmd = frames.decode_dp0_command(f.data, cfg.protocol)
            assert isinstance(cmd, frames.Dp0Command)
            a, b = (
                yx_to_ab(cmd.cmd_ay, cmd.cmd_bx)
                if cfg.velocity_model == "travel"
                else (cmd.cmd_ay, cmd.cmd_bx)
            )
            out.append((f.start, a, b, cmd.inputs))
    return out


def assert_stopped(bench: FakeBench, unit: str) -> None:
    """The drive stands still with its servo off, and the last command was the safe word."""
    drive = bench.drive(unit)
    assert drive.vel == pytest.approx([0.0, 0.0], abs=0.5)
    assert not drive.inputs & (drive.layout.servo.both | drive.layout.start.both)
    _, a, b, inputs = commands(bench, unit)[-1]
    layout = flags.layout(bench.config.units[unit].protocol)
    assert (a, b) == (0.0, 0.0) and is_safe_word(inputs, layout)


# ---------------------------------------------------------------- the demo


def test_the_demo_passes_front_and_names_rear_motor_b_reversed_with_its_fix() -> None:
    bench = FakeBench(load_config("configs/commission-demo.yaml"))
    results, why, _ = session(bench, Settings())
    assert why is None
    assert results["front"].verdict is Verdict.PASS
    rear = results["rear"]
    assert rear.verdict is Verdict.FAIL
    assert failed(rear) == ["reversed axis B (+150 min⁻¹)"]
    fix = next(c.fix for c in rear.checks if c.verdict is Verdict.FAIL)
    assert "polarity" in fix and "0x4000–0x4083" in fix and "encoder" in fix
    # motor A of rear passed its jog before B was tried
    assert any(c.step == "jog A" and c.verdict is Verdict.PASS for c in rear.checks)
    for unit in ("front", "rear"):
        assert_stopped(bench, unit)


# ---------------------------------------------------------------- every wiring fault

CASES = {
    "reversed_axis A": ("{kind: reversed_axis, unit: u1, axis: A}", "reversed axis A", "polarity"),
    "reversed_axis B": ("{kind: reversed_axis, unit: u1, axis: B}", "reversed axis B", "polarity"),
    "swapped_axes": ("{kind: swapped_axes, unit: u1}", "swapped axes", "cables"),
    "scale": (
        "{kind: scale, unit: u1, axis: B, factor: 1.2}",
        "gear/geometry scale of motor B off by +20%",
        "geometry.pulses_per_rev: 122",  # 1.2 × 1024 = 1229, within the integration
    ),
    "no_encoder": ("{kind: no_encoder, unit: u1, axis: A}", "no encoder on motor A", "encoder"),
    "other_velocity_model": (
        "{kind: other_velocity_model, unit: u1}",
        "velocity model",
        "velocity_model: travel",
    ),
}


@pytest.mark.parametrize("gen", ["2021", "2023"])
@pytest.mark.parametrize("case", list(CASES))
def test_each_wiring_fault_is_named_with_its_fix_and_the_right_drive_passes(
    case: str, gen: str
) -> None:
    fault, name, fix = CASES[case]
    bench = robot(fault, gen)
    results, why, _ = session(bench)
    assert why is None
    assert results["u2"].verdict is Verdict.PASS, results["u2"].checks
    u1 = results["u1"]
    fails = [c for c in u1.checks if c.verdict is Verdict.FAIL]
    assert [c.name for c in fails][:1] == [name] or fails[0].name.startswith(name), fails
    assert fix in fails[0].fix
    for unit in ("u1", "u2"):
        assert_stopped(bench, unit)


@pytest.mark.parametrize("gen", ["2021", "2023"])
def test_a_reversed_axis_is_found_on_a_travel_model_drive_too(gen: str) -> None:
    bench = robot("{kind: reversed_axis, unit: u1, axis: B}", gen, model="travel")
    results, _, _ = session(bench)
    assert failed(results["u1"]) == ["reversed axis B (+100 min⁻¹)"]
    assert results["u2"].verdict is Verdict.PASS


def test_the_jog_never_commands_beyond_its_limits() -> None:
    """From the DP0 command frames on the wire: every value within the jog speed."""
    bench = robot("{kind: swapped_axes, unit: u1}")
    results, _, _ = session(bench)
    speed = FAST.jog_speed(2000)
    assert speed == 100.0
    for unit in ("u1", "u2"):
        sent = commands(bench, unit)
        assert max(max(abs(a), abs(b)) for _, a, b, _ in sent) <= speed + 1e-9
        # one motor at a time
        assert all(a == 0 or b == 0 for _, a, b, _ in sent)
    assert results["u2"].verdict is Verdict.PASS


def test_a_wrong_encoder_stops_the_unit_before_the_jog_ends() -> None:
    bench = robot("{kind: reversed_axis, unit: u1, axis: A}")
    results, _, _ = session(bench, units=["u1"])
    jog = results["u1"].traces[0]
    assert jog.stopped is not None and "against the command" in jog.stopped
    moving = [t for t, a, _, _ in commands(bench, "u1") if a]
    assert moving[-1] - moving[0] < 0.3  # far less than the 0.5 s asked
    assert bench.drive("u1").inputs & bench.drive("u1").layout.servo.both == 0


def _jog_a_starts() -> float:
    """When jog A's first frame goes out (the fake clock runs the same up to a fault)."""
    bench = robot()
    session(bench, units=["u1"])
    return next(t for t, a, _, _ in commands(bench, "u1") if a)


@pytest.mark.parametrize(
    "into", [0.2, FAST.jog_s + 0.02], ids=["mid-jog", "in the pause before the reversal"]
)
def test_a_drive_gone_silent_is_stopped_within_a_quarter_second_and_named(into: float) -> None:
    """Silence is a fault: no jog or reversal is commanded later than 0.25 s after the
    drive's last answer (judged from the frames), and the report names the link, not the
    power stage."""
    silent_at = _jog_a_starts() + into
    bench = robot(f"{{kind: silent, unit: u1, at_s: {silent_at}, for_s: 60}}")
    results, _, operator = session(bench, units=["u1"])
    cfg = bench.config.units["u1"]
    reply = ids.dp0_reply_id(cfg.abh3_id, cfg.host_id)
    answers = [f.start for f in bench.timeline.frames if f.node != 0 and f.arbitration_id == reply]
    last_answer = max(answers)
    assert silent_at - 0.03 < last_answer <= silent_at  # the fault, not something else
    moving = [t for t, a, b, _ in commands(bench, "u1") if a or b]
    assert moving and moving[-1] <= last_answer + 0.25, moving[-1] - last_answer
    assert not [t for t, a, _, _ in commands(bench, "u1") if a < 0]  # no reversal
    assert_stopped(bench, "u1")
    jog = [c for c in results["u1"].checks if c.step == "jog A"]
    assert [c.name for c in jog] == ["communication lost"], jog
    assert "no answer from the drive" in jog[0].measured
    assert "termination" in jog[0].fix and "CAN settings" in jog[0].fix
    assert not any("power stage" in c.fix for c in results["u1"].checks)
    assert results["u1"].verdict is Verdict.FAIL
    assert any(line.startswith("  STOPPED unit u1: no answer") for line in operator.lines)


def test_the_e_stop_figure_is_within_one_command_period() -> None:
    bench = robot()
    results, _, _ = session(bench, units=["u1"])
    (check,) = [c for c in results["u1"].checks if c.step == "e-stop"]
    assert check.verdict is Verdict.PASS
    latency = float(check.measured.split()[0]) / 1000
    assert 0 <= latency <= 1 / 50
    # and it is what the wire shows: the first frame without START after the key
    starts = [(t, i) for t, _, _, i in commands(bench, "u1")]
    layout = flags.layout(Generation.G2021)
    armed = [t for t, i in starts if i & layout.start.both]
    first_stop = next(t for t, i in starts if t > armed[0] and not i & layout.start.both)
    assert first_stop - armed[-1] <= 1 / 50 + 1e-9


def test_a_stalled_sequence_lets_the_jog_lapse_to_zero() -> None:
    """The commissioning input's commands lapse after its timeout: a sequence that stops
    repeating them (hung) stops the motor through the arbitration."""
    bench = robot()
    bench.sup.apply_text("u1", "SERVO ON ON")
    bench.sup.apply_text("u1", "START ON ON")
    bench.move("u1", 100, 0)
    bench.run(1.0)  # nobody repeats it
    sent = commands(bench, "u1")
    moving = [t for t, a, _, _ in sent if a]
    assert moving and moving[-1] - moving[0] <= 0.3 + 0.02
    assert sent[-1][1:3] == (0.0, 0.0)
    assert bench.drive("u1").vel[0] == pytest.approx(0.0, abs=1.0)


def test_e_stop_outside_the_rehearsal_ends_the_session_with_everything_stopped() -> None:
    bench = robot()

    class Presses(Headless):
        async def confirm(self, question: str) -> bool:
            if "jog motor B" in question:
                self.bench.sup.emergency_stop()  # the operator's key, mid-session
            return True

    operator = Presses(bench)
    results: dict[str, UnitResult] = {}
    why = asyncio.run(commission(bench, operator, ["u1", "u2"], FAST, results))
    bench.run(0.5)
    assert why == "e-stop pressed"
    assert "aborted" in failed(results["u1"]) and "aborted" in failed(results["u2"])
    for unit in ("u1", "u2"):
        assert bench.drive(unit).vel == pytest.approx([0.0, 0.0], abs=0.5)


def cancel_mid_jog(bench: FakeBench, units: list[str]) -> dict[str, UnitResult]:
    """Run the sequence on ``units`` and cancel it (as Ctrl-C does) once u1 moves."""
    results: dict[str, UnitResult] = {}

    async def main() -> None:
        task = asyncio.ensure_future(commission(bench, Headless(bench), units, FAST, results))
        while not any(a for _, a, _, _ in commands(bench, "u1")):
            await asyncio.sleep(0)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())
    bench.run(0.5)
    return results


def test_cancelling_mid_jog_stops_the_drive() -> None:
    """Ctrl-C reaches the sequence as a cancellation: the unit it moves is stopped."""
    bench = robot()
    cancel_mid_jog(bench, ["u1"])
    assert_stopped(bench, "u1")


def test_a_session_cancelled_mid_jog_fails_the_unit_it_interrupted_and_those_not_begun() -> None:
    """Ctrl-C after u1's identity and e-stop passed: u1 is not a pass (its wiring was never
    judged), and u2, never begun, is not commissioned."""
    bench = robot()
    results = cancel_mid_jog(bench, ["u1", "u2"])
    u1, u2 = results["u1"], results["u2"]
    assert any(c.step == "e-stop" and c.verdict is Verdict.PASS for c in u1.checks)
    assert u1.verdict is Verdict.FAIL and failed(u1) == ["interrupted"]
    assert u2.verdict is Verdict.FAIL and failed(u2) == ["interrupted"]
    assert u1.checks[-1].measured == "the session was stopped during its sequence"
    assert u2.checks[-1].measured == "not commissioned: the session was stopped before it began"
    assert not commands(bench, "u2") or not any(a or b for _, a, b, _ in commands(bench, "u2"))
    assert_stopped(bench, "u1")


def test_monitor_and_moving_units_are_refused() -> None:
    text = ROBOT.format(faults="", gen="2021", model="motor", tau=50).replace(
        "host_id: 9,", "host_id: 9, role: monitor,"
    )
    bench = FakeBench(parse_config(text, "robot.yaml"))
    results, _, _ = session(bench, units=["u2"])
    assert failed(results["u2"]) == ["role"]
    assert not [f for f in bench.timeline.frames if f.arbitration_id == ids.dp0_command_id(3, 9)]

    bench = robot()
    bench.sup.apply_text("u1", "SERVO ON ON")
    bench.sup.apply_text("u1", "START ON ON")
    set_velocity_ab(
        bench.sup, "u1", 50, 0, source=present(bench.sup, "u1")
    )  # someone else's setpoint, before we start
    bench.run(0.5)
    set_velocity_ab(bench.sup, "u1", 50, 0, source=present(bench.sup, "u1"))
    results, _, _ = session(bench, units=["u1"])
    assert "at rest" in failed(results["u1"])
    assert not [c for c in results["u1"].checks if c.step.startswith("jog")]


def test_a_unit_whose_startup_sets_it_moving_is_refused() -> None:
    """The file's startup: is not run, but a unit it would set moving is not at rest as the
    robot is used: refused, never commanded beyond its idle word."""
    bench = robot()
    results: dict[str, UnitResult] = {}
    startups = {"u1": ("SERVO ON ON", "START ON ON", "VEL 100 0"), "u2": ("SERVO ON ON",)}
    asyncio.run(commission(bench, Headless(bench), ["u1", "u2"], FAST, results, startups))
    bench.run(0.5)
    u1 = results["u1"]
    assert failed(u1) == ["at rest"], u1.checks
    assert "'VEL 100 0'" in next(c.measured for c in u1.checks if c.name == "at rest")
    assert not [c for c in u1.checks if c.step.startswith(("jog", "step"))]
    assert {c.verdict for c in u1.checks if c.step == "e-stop"} == {Verdict.SKIPPED}
    layout = flags.layout(Generation.G2021)
    sent = commands(bench, "u1")
    assert sent and all(a == b == 0 and is_safe_word(i, layout) for _, a, b, i in sent)
    assert results["u2"].verdict is Verdict.PASS  # SERVO ON alone moves nothing


def test_a_jog_too_slow_to_judge_is_a_fail_not_a_pass_of_nothing() -> None:
    """limits.velocity 30 × 5 % rounds to a jog of 1.2 min⁻¹: too slow to judge."""
    text = ROBOT.format(faults="", gen="2023", model="motor", tau=50)
    bench = FakeBench(parse_config(text.replace("velocity: 2000", "velocity: 30"), "r.yaml"))
    results, _, _ = session(bench, units=["u1"])
    u1 = results["u1"]
    assert failed(u1) == ["jog speed"] and "below the 2 min⁻¹" in u1.checks[-1].fix
    assert not [c for c in u1.checks if c.step.startswith(("jog", "step"))]
    assert not any(a or b for _, a, b, _ in commands(bench, "u1"))


@pytest.mark.parametrize("gen", ["2021", "2023"])
def test_a_unit_in_current_control_is_jogged_in_velocity_control(gen: str) -> None:
    """`control: current` sets the torque bits at start; the bring-up's jogs are velocity
    commands (they were refused, and the report blamed the power stage)."""
    text = ROBOT.format(
        faults="{kind: reversed_axis, unit: u1, axis: B}", gen=gen, model="motor", tau=50
    )
    bench = FakeBench(
        parse_config(text.replace("abh3_id: 1,", "abh3_id: 1, control: current,"), "c.yaml")
    )
    results, _, _ = session(bench, units=["u1"])
    assert failed(results["u1"]) == ["reversed axis B (+100 min⁻¹)"], results["u1"].checks
    layout = flags.layout(Generation(gen))
    moving = [(a, i) for _, a, _, i in commands(bench, "u1") if a]
    assert moving and all(not i & layout.torque.both for _, i in moving)
    assert max(abs(a) for a, _ in moving) <= 100
    assert_stopped(bench, "u1")


def test_a_unit_whose_data_select_stops_an_axis_is_refused() -> None:
    """data_select 0 is set #7 & STOP: a jog could only fail, blaming the power stage."""
    text = ROBOT.format(faults="", gen="2021", model="motor", tau=50)
    text = text.replace("abh3_id: 1,", "abh3_id: 1, data_select: {ay: 7, bx: 0},")
    bench = FakeBench(parse_config(text, "d.yaml"))
    results, _, _ = session(bench, units=["u1"])
    u1 = results["u1"]
    assert failed(u1) == ["data select"]
    assert "data_select.bx" in next(c.fix for c in u1.checks if c.name == "data select")
    assert not any(a or b for _, a, b, _ in commands(bench, "u1"))


def test_without_consent_nothing_moves() -> None:
    bench = robot()
    operator = Headless(bench, answers=False)
    results: dict[str, UnitResult] = {}
    asyncio.run(commission(bench, operator, ["u1"], FAST, results))
    assert not any(a or b for _, a, b, _ in commands(bench, "u1"))
    assert results["u1"].verdict is Verdict.WARN  # checked what it could; motion not run


# ---------------------------------------------------------------- the report


class _Refs(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.polylines: list[dict[str, str | None]] = []
        self.panels: list[dict[str, str | None]] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append(tag)
        a = dict(attrs)
        if tag == "polyline":
            self.polylines.append({**a, "panel": self.panels[-1]["data-panel"]})
        elif tag == "g" and "data-panel" in a:
            self.panels.append(a)


def _report(bench: FakeBench, results: dict[str, UnitResult]) -> Session:
    return Session(
        "abh3-supervisor test",
        "2026-01-01T00:00:00+00:00",
        "robot.yaml",
        bench.config.text,
        FAST,
        results,
    )


def test_the_html_is_self_contained_and_its_plots_are_the_recorded_feedback() -> None:
    bench = robot("{kind: reversed_axis, unit: u1, axis: B}")
    results, _, _ = session(bench)
    s = _report(bench, results)
    page = html_text(s)
    assert not re.search(r"(?i)(https?:|//|<script|<link|@import|url\(|src=)", page)
    parser = _Refs()
    parser.feed(page)
    assert {"svg", "polyline", "table"} <= set(parser.tags)
    doc = to_json(s)
    traces = [t for u in doc["units"].values() for t in u["traces"]]
    feedback = [p for p in parser.polylines if p["data-series"] in ("feedback-a", "feedback-b")]
    assert len(feedback) == 2 * len(traces) > 0
    panels = [p for p in parser.panels if p["data-panel"] == "velocity min⁻¹"]
    for i, trace in enumerate(traces):
        panel = panels[i]
        t0, t1 = float(panel["data-t0"] or 0), float(panel["data-t1"] or 0)
        y0, y1 = float(panel["data-y0"] or 0), float(panel["data-y1"] or 0)
        top = float(panel["data-top"] or 0)
        for series, key in ((feedback[2 * i], "a"), (feedback[2 * i + 1], "b")):
            points = [tuple(map(float, p.split(","))) for p in (series["points"] or "").split()]
            t = [t0 + (x - LEFT) / (WIDTH - LEFT - RIGHT) * (t1 - t0) for x, _ in points]
            v = [y0 + (top + PANEL - y) / PANEL * (y1 - y0) for _, y in points]
            assert t == pytest.approx(trace["feedback"]["t"], abs=0.01 * (t1 - t0))
            assert v == pytest.approx(trace["feedback"][key], abs=0.01 * (y1 - y0))
    # the JSON's feedback is what the drive answered: each DP0 reply of u1, in order
    u1 = bench.config.units["u1"]
    replies = [
        frames.decode_dp0_reply(f.data, Generation.G2021)
        for f in bench.timeline.frames
        if f.arbitration_id == ids.dp0_reply_id(u1.abh3_id, u1.host_id)
    ]
    answered = [(r.vel_a, r.vel_b) for r in replies if isinstance(r, frames.Dp0Reply2021)]
    jog = doc["units"]["u1"]["traces"][0]
    seen = list(zip(jog["feedback"]["a"], jog["feedback"]["b"], strict=True))
    n = len(seen)
    assert any(answered[i : i + n] == seen for i in range(len(answered) - n + 1))
    assert '"verdict": "fail"' in json_text(s)


# ---------------------------------------------------------------- pure judgements


def test_step_metrics_of_a_first_order_response() -> None:
    tau, size = 0.05, 100.0
    trace = Trace("step A", "step", 0, 0.0)
    trace.feedback = [
        (t / 1000, size * (1 - math.exp(-t / 1000 / tau)), 0.0) for t in range(0, 801, 2)
    ]
    trace.current = [(0.01, 40.0, 0.0), (0.3, 5.0, 0.0)]
    m = analysis.step_metrics(trace, 0, size, 0.0, 0.8)
    assert m.rise_s == pytest.approx(tau * math.log(9), abs=0.003)
    assert m.settling_s == pytest.approx(tau * math.log(20), abs=0.003)
    assert m.overshoot == 0.0 and m.steady_error < 0.001 and m.peak_current == 40.0
    checks = analysis.judge_step(trace, m, Settings(), 0)
    assert all(c.verdict is Verdict.PASS for c in checks)


def test_pulses_per_rev_from_counts_and_the_integrated_feedback() -> None:
    trace = Trace("jog A", "jog", 0, 0.0)
    trace.feedback = [(i * 0.02, 60.0, 0.0) for i in range(51)]  # one revolution a second
    trace.pulses = [(0.0, 0, 0), (0.5, 600, 0), (1.0, 1200, 0)]
    assert analysis.measured_pulses_per_rev(trace, 0) == pytest.approx(1200)
    assert analysis.judge_scale(trace, 0, 1024, Settings()).verdict is Verdict.FAIL
    assert analysis.judge_scale(trace, 0, 1200, Settings()).verdict is Verdict.PASS
    assert analysis.judge_scale(trace, 0, 0, Settings()).verdict is Verdict.WARN


def test_without_pulses_per_rev_motors_that_count_alike_pass_and_unlike_fail() -> None:
    s = Settings()
    assert analysis.judge_pair("jog B", 4096, 4080, s).verdict is Verdict.PASS
    unlike = analysis.judge_pair("jog B", 4096, 4096 * 1.2, s)
    assert unlike.verdict is Verdict.FAIL and unlike.name.endswith("+20% against motor A")
    assert analysis.judge_pair("jog B", None, 4096, s).verdict is Verdict.WARN  # not counted


def test_settings_outside_their_bounds_are_refused() -> None:
    with pytest.raises(
        SettingsError, match=r"--jog-fraction 0.5 is out of bounds \(allowed 0.01–0.2"
    ):
        Settings(jog_fraction=0.5).check()
    with pytest.raises(SettingsError, match="--jog-seconds 2 is out of bounds"):
        Settings(jog_s=2.0).check()


PLAIN = """
buses:
  robot: {{interface: virtual, channel: p, simulate: {{faults: [{faults}]}}}}
units:
  - {{name: u1, abh3_id: 1, protocol: "{gen}"}}
  - {{name: u2, abh3_id: 3, protocol: "{gen}"}}
"""


@pytest.mark.parametrize("gen", ["2021", "2023"])
@pytest.mark.parametrize(
    ("fault", "name"),
    [
        ("{kind: scale, unit: u1, axis: A, factor: 0.8}", "gear/geometry scale: motor B counts"),
        ("{kind: reversed_axis, unit: u1, axis: A}", "reversed axis A"),
        ("{kind: swapped_axes, unit: u1}", "swapped axes"),
        ("{kind: no_encoder, unit: u1, axis: B}", "no encoder on motor B"),
    ],
)
def test_a_plain_file_finds_the_faults_too(fault: str, name: str, gen: str) -> None:
    """The defaults everywhere: travel model, the ramp at accel, the wire's whole velocity
    range (jog 327.6 min⁻¹), no geometry.pulses_per_rev (motors held against each other)."""
    bench = FakeBench(parse_config(PLAIN.format(faults=fault, gen=gen), "plain.yaml"))
    results, _, _ = session(bench)
    assert failed(results["u1"])[0].startswith(name), results["u1"].checks
    # pulses per revolution not in the file: its motors agree with each other, a pass
    assert results["u2"].verdict is Verdict.PASS, results["u2"].checks
    (pair,) = [c for c in results["u2"].checks if c.name == "gear/geometry scale of motors A and B"]
    assert "geometry.pulses_per_rev" in pair.measured
    speed = Settings().jog_speed(6553.4)
    for unit in ("u1", "u2"):
        assert max(max(abs(a), abs(b)) for _, a, b, _ in commands(bench, unit)) <= speed
        assert_stopped(bench, unit)
