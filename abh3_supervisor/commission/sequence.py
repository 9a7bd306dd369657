"""The commissioning sequence of one unit: identity and settings, e-stop rehearsal,
direction and wiring per motor, step response per motor, summary.

It runs against a :class:`Bench` — the clock, motion through the input arbitration (a
source of its own whose commands lapse unless repeated, so a stalled sequence stops the
jog), the wire's frames and the parameter channel — and an :class:`Operator` (questions,
the e-stop key). The terminal client provides both on a live runtime; tests provide them
on a fake clock. A :class:`~.guard.Guard` watches every answer while a unit moves and
stops it at once with the safe word; the e-stop (``Supervisor.estop``) ends the session.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from abh3_supervisor.commission import analysis
from abh3_supervisor.commission.analysis import Phase
from abh3_supervisor.commission.guard import Guard
from abh3_supervisor.commission.model import AXES, Check, Settings, Trace, Verdict
from abh3_supervisor.config.model import Role, UnitConfig, VelocityModel
from abh3_supervisor.core.kinematics import yx_to_ab
from abh3_supervisor.core.supervisor import Supervisor, SupervisorEvent
from abh3_supervisor.core.verify import State, Verification
from abh3_supervisor.errors import Abh3Error, CommandError
from abh3_supervisor.params import table
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.scheduler.core import FeedbackEvent, StatusEvent

log = logging.getLogger(__name__)
REFRESH_S = 0.05  # the sequence repeats its command this often (the source lapses at 0.3 s)
SOURCE_TIMEOUT_S = 0.3
RATE_WINDOW_S = 1.0
MOVING = 0.01  # of limits.velocity (at least 2 min⁻¹): a unit turning faster is refused
# what the report shows of the drive's set-up beside its CAN settings: the selected data
# set's speed, current, ramps and gains (data select 7 = set #0), which the fixes name
PARAMS_READ = (
    0x4100,
    0x4101,
    0x4102,
    0x4103,
    0x4105,
    0x4107,
    0x4117,
    0x4118,
    0x5000,
    0x5008,
    0x5010,
    0x5018,
    0x5020,
    0x5040,
    0x5060,
    0x5070,
)


class Aborted(Exception):
    """The e-stop was pressed outside its rehearsal: the session ends, drives stopped."""


class Bench(Protocol):
    sup: Supervisor

    def now(self) -> float: ...
    async def wait(self, seconds: float) -> None: ...
    def move(self, unit: str, a: float, b: float) -> None:
        """Motors A and B [min⁻¹], as the commissioning input's command (arbitrated)."""

    def release(self, unit: str) -> None:
        """The commissioning input lets go of ``unit``: zero at once."""

    def wire(self) -> Sequence[tuple[float, int, bytes]]:
        """Every frame the host sent, (time, identifier, data), in order."""

    async def identity(self, unit: str) -> str: ...
    async def read_param(self, unit: str, address: int) -> int: ...
    async def verification(self, unit: str) -> Verification: ...


class Operator(Protocol):
    def say(self, text: str) -> None: ...
    async def confirm(self, question: str) -> bool: ...
    async def press_estop(self, prompt: str) -> float | None:
        """The bench time at which the operator pressed the e-stop key (the key itself
        latches the supervisor's e-stop); None if it was not pressed."""


@dataclass
class UnitResult:
    cfg: UnitConfig
    checks: list[Check] = field(default_factory=list)
    traces: list[Trace] = field(default_factory=list)
    firmware: str | None = None
    params: dict[int, str] = field(default_factory=dict)
    settings_rows: list[dict[str, Any]] = field(default_factory=list)
    ended: str | None = None  # why the sequence ended early for this unit

    @property
    def verdict(self) -> Verdict:
        verdicts = {c.verdict for c in self.checks}
        if Verdict.FAIL in verdicts or not self.checks:
            return Verdict.FAIL
        if verdicts & {Verdict.WARN, Verdict.SKIPPED}:
            return Verdict.WARN
        return Verdict.PASS

    def add(self, check: Check) -> Check:
        self.checks.append(check)
        return check


class Collector:
    """Fills the unit's open trace from the supervisor's events: DP0 feedback on every
    exchange, currents (broadcast 3) and pulse counts (broadcast 4)."""

    def __init__(self, sup: Supervisor, unit: str) -> None:
        self.sup, self.unit = sup, unit
        self.trace: Trace | None = None
        self.feedbacks = 0
        self.statuses = 0

    def __call__(self, event: SupervisorEvent) -> None:
        if getattr(event, "unit", None) != self.unit:
            return
        if isinstance(event, FeedbackEvent):
            self.feedbacks += 1
            fb = self.sup.units[self.unit].feedback
            if self.trace is not None and fb is not None and fb.t == event.t:
                self.trace.feedback.append((event.t - self.trace.t0, fb.vel_a, fb.vel_b))
        elif isinstance(event, StatusEvent):
            self.statuses += 1
            record, trace = event.record, self.trace
            if trace is None:
                return
            if isinstance(record, frames.Brd3):
                trace.current.append((event.t - trace.t0, record.cur_cmd_ay, record.cur_cmd_bx))
            elif isinstance(record, frames.Brd4):
                trace.pulses.append((event.t - trace.t0, record.pulse_a, record.pulse_b))


def halt(bench: Bench, unit: str) -> None:
    """Stop ``unit`` now: the input lets go and the unit gets the safe word (zero, SERVO,
    START and every other switch off; data select kept). Never raises."""
    sup = bench.sup
    try:
        bench.release(unit)
    except Exception:
        log.exception("releasing %s failed; stopping it anyway", unit)
    state = sup.units[unit]
    if state.cfg.role is not Role.COMMAND or sup.stopping:
        return
    try:
        sup.set_inputs(unit, state.layout.safe(state.inputs), 0xFFFFFFFF)
        sup.zero(unit)
    except CommandError as exc:  # only turning things off: should not happen
        log.error("stopping %s: %s", unit, exc)


class UnitSequence:
    def __init__(self, bench: Bench, operator: Operator, unit: str, settings: Settings) -> None:
        self.bench, self.op, self.settings = bench, operator, settings
        self.sup = bench.sup
        self.state = self.sup.units[unit]
        self.cfg = self.state.cfg
        self.unit = unit
        self.result = UnitResult(self.cfg)
        self.speed = settings.jog_speed(self.cfg.limits.velocity)
        self.collector = Collector(self.sup, unit)
        self.counted: list[float | None] = [None, None]  # pulses per revolution, A and B

    # ------------------------------------------------------------ helpers

    def _check(self, step: str, name: str, verdict: Verdict, measured: str, *rest: str) -> None:
        check = self.result.add(Check(step, name, verdict, measured, *rest))
        mark = {"pass": "ok", "warn": "WARN", "fail": "FAIL", "not run": "--"}[verdict.value]
        fix = f" → {check.fix}" if check.fix and verdict is not Verdict.PASS else ""
        self.op.say(f"  [{mark:>4}] {step}: {name}: {measured}{fix}")

    async def _wait(self, seconds: float) -> None:
        await self.bench.wait(seconds)
        if self.sup.estop:
            raise Aborted("e-stop pressed")

    async def _until(self, ready: Callable[[], bool], timeout: float) -> bool:
        end = self.bench.now() + timeout
        while not ready():
            if self.bench.now() >= end:
                return False
            await self._wait(0.02)
        return True

    def _skip(self, steps: Sequence[str], why: str) -> None:
        for step in steps:
            self._check(step, "not run", Verdict.SKIPPED, why)
        self.result.ended = self.result.ended or why

    # ------------------------------------------------------------ the steps

    async def run(self) -> UnitResult:
        self.sup.subscribe(self.collector)
        try:
            if await self.identity():
                await self.motion()
        finally:
            self.sup.unsubscribe(self.collector)
            halt(self.bench, self.unit)
        return self.result

    async def identity(self) -> bool:
        """Step 1; True when motion may follow."""
        cfg, state = self.cfg, self.state
        self.op.say(
            f"unit {self.unit}: drive {cfg.abh3_id} on bus {cfg.bus}, protocol "
            f"{cfg.protocol}, velocity_model {cfg.velocity_model}"
        )
        if cfg.role is not Role.COMMAND:
            self._check(
                "identity",
                "role",
                Verdict.FAIL,
                "role: monitor",
                "role: command",
                "commissioning moves the motors: a monitor unit is refused; set "
                "role: command for the bring-up",
            )
            self._skip(["e-stop", "motion"], "refused: role: monitor")
            return False
        online = await self._until(lambda: bool(state.online), cfg.timeout_ms / 1000 + 1.0)
        if not online:
            self._check(
                "identity",
                "online",
                Verdict.FAIL,
                "no answer",
                f"abh3_id {cfg.abh3_id}",
                "abh3 scan finds the drive's address and host; check abh3_id, host_id, "
                "the bus bitrate and wiring (docs/hardware.md, troubleshooting)",
            )
            self._skip(["e-stop", "motion"], "offline")
            return False
        self._check("identity", "online", Verdict.PASS, f"drive {cfg.abh3_id} answers")
        await self._firmware()
        await self._settings()
        await self._rates()
        ok = await self._flags()
        fb = state.feedback
        still = max(2.0, MOVING * cfg.limits.velocity)
        if fb is not None and max(abs(fb.vel_a), abs(fb.vel_b)) > still:
            self._check(
                "identity",
                "at rest",
                Verdict.FAIL,
                f"A {fb.vel_a:+.1f}, B {fb.vel_b:+.1f} min⁻¹",
                f"|v| ≤ {still:g} min⁻¹",
                "the unit is already moving: stop whatever drives it first",
            )
            ok = False
        if state.verify.holds():
            why = "verify: refuse holds the unit at its idle word (its settings differ)"
            self._check(
                "identity",
                "commandable",
                Verdict.FAIL,
                why,
                "",
                "fix the settings above, or verify: warn",
            )
            ok = False
        if not ok:
            self._skip(["e-stop", "motion"], "identity checks failed")
        return ok

    async def _firmware(self) -> None:
        try:
            self.result.firmware = await self.bench.identity(self.unit)
        except Abh3Error as exc:
            self._check(
                "identity",
                "firmware version",
                Verdict.WARN,
                f"not read: {exc}",
                "",
                "the drive's parameter channel (docs/parameters.md)",
            )
            return
        self._check("identity", "firmware version", Verdict.PASS, self.result.firmware)
        for address in PARAMS_READ:
            try:
                word = await self.bench.read_param(self.unit, address)
            except Abh3Error as exc:
                self.result.params[address] = f"not read: {exc}"
                continue
            value = table.to_value(word, table.kind_of(address))
            self.result.params[address] = table.display(value)

    async def _settings(self) -> None:
        v = await self.bench.verification(self.unit)
        self.result.settings_rows = [row.to_json() for row in v.rows]
        if v.state is State.OK:
            self._check("identity", "CAN settings", Verdict.PASS, f"{len(v.rows)} agree with YAML")
        elif v.state is State.MISMATCH:
            for row in v.rows:
                if row.mismatch:
                    self._check(
                        "identity",
                        f"CAN setting 0x{row.address:04X} {row.name}",
                        Verdict.FAIL,
                        f"drive {row.drive}",
                        f"YAML {row.yaml}",
                        f"set the drive (abh3 param set {self.unit} "
                        f"0x{row.address:04X} …) or the YAML",
                    )
        else:
            self._check(
                "identity",
                "CAN settings",
                Verdict.WARN,
                f"{v.state}: {v.reason or ''}".rstrip(": "),
                "",
                "abh3 check CONFIG --drives once the drive answers parameter requests",
            )

    async def _rates(self) -> None:
        cfg = self.cfg
        before = self.collector.feedbacks, self.collector.statuses
        await self._wait(RATE_WINDOW_S)
        dp0 = (self.collector.feedbacks - before[0]) / RATE_WINDOW_S
        brd = (self.collector.statuses - before[1]) / RATE_WINDOW_S
        want = cfg.command_rate_hz
        verdict = Verdict.PASS if dp0 >= 0.9 * want else Verdict.WARN
        self._check(
            "identity",
            "DP0 exchange rate",
            verdict,
            f"{dp0:.1f} /s",
            f"{want:g} /s",
            ""
            if verdict is Verdict.PASS
            else "lower command_rate_hz or the bus load "
            "(`abh3 check` shows the plan); slow replies: 0x4105",
        )
        if cfg.broadcast.packets and not cfg.broadcast.listen_only:
            want = cfg.broadcast.rate_hz
            verdict = Verdict.PASS if brd >= 0.9 * want else Verdict.WARN
            self._check(
                "identity",
                "broadcast rate",
                verdict,
                f"{brd:.1f} /s",
                f"{want:g} /s",
                ""
                if verdict is Verdict.PASS
                else "broadcast.rate_hz, broadcast group 0x4107 (brd_group)",
            )

    async def _fresh(self, packet: int) -> None:
        since = self.bench.now()
        seen = self.state.status.get(packet)
        self.sup.request_status(self.unit, packet)
        await self._until(
            lambda: (
                (s := self.state.status.get(packet)) is not None and s is not seen and s[0] >= since
            ),
            self.cfg.timeout_ms / 1000,
        )

    async def _flags(self) -> bool:
        """Errors and alarms by name; the velocity model the drive reports."""
        await self._fresh(0)
        error = self.state.words.get("error")
        alarm = self.state.words.get("alarm", 0)
        ok = True
        if error is None:
            self._check("identity", "errors", Verdict.WARN, "broadcast 0 not answered")
        elif error:
            names = ", ".join(flags.FAULT.labels(error))
            self._check(
                "identity",
                "errors",
                Verdict.FAIL,
                names,
                "none",
                "remove the cause, then reset the error (SERVO OFF, error reset)",
            )
            ok = False
        else:
            self._check("identity", "errors", Verdict.PASS, "none")
        if alarm:
            self._check(
                "identity",
                "alarms",
                Verdict.WARN,
                ", ".join(flags.FAULT.labels(alarm)),
                "none",
                "see docs/hardware.md, troubleshooting",
            )
        else:
            self._check("identity", "alarms", Verdict.PASS, "none")
        if self.cfg.protocol is Generation.G2021:
            await self._fresh(1)
        else:
            await self._until(lambda: "control" in self.state.words, 0.5)
        control = self.state.words.get("control")
        if control is None:
            self._check("identity", "velocity model", Verdict.WARN, "control word not read")
            return ok
        travel = bool(control & self.state.layout.travel_model)
        drive = VelocityModel.TRAVEL if travel else VelocityModel.MOTOR
        if drive is not self.cfg.velocity_model:
            self._check(
                "identity",
                "velocity model",
                Verdict.FAIL,
                f"drive: {drive}",
                f"YAML velocity_model: {self.cfg.velocity_model}",
                f"velocity_model: {drive} in the YAML (or the drive's axis model)",
            )
            return False
        self._check("identity", "velocity model", Verdict.PASS, str(drive))
        return ok

    # ------------------------------------------------------------ e-stop and motion

    async def estop(self) -> None:
        """Step 2: START on (servo off: nothing is energised), the operator presses the
        e-stop, and the first frame carrying the stop is found on the wire."""
        period = 1 / self.cfg.command_rate_hz
        try:
            self.sup.set_inputs(
                self.unit, self.state.layout.start.both, self.state.layout.start.both
            )
        except CommandError as exc:
            self._check("e-stop", "rehearsal", Verdict.FAIL, str(exc))
            return
        await self._wait(3 * period)
        key = await self.op.press_estop(
            f"unit {self.unit}: e-stop rehearsal — press the e-stop key (e) now"
        )
        if key is None:
            self._check(
                "e-stop",
                "rehearsal",
                Verdict.FAIL,
                "the key was not pressed",
                "",
                "press the e-stop key when asked",
            )
            return
        await self.bench.wait(3 * period)
        frame = self._first_stop_frame(key)
        self.sup.clear_emergency_stop()
        check = analysis.judge_estop(None if frame is None else frame - key, period)
        self._check(check.step, check.name, check.verdict, check.measured, check.limit, check.fix)

    def _command_id(self) -> int:
        return ids.dp0_command_id(self.cfg.abh3_id, self.cfg.host_id) & 0x03FFFFFF

    def _first_stop_frame(self, since: float) -> float | None:
        start = self.state.layout.start.both
        for t, arbitration_id, data in self.bench.wire():
            if t < since or arbitration_id & 0x03FFFFFF != self._command_id():
                continue
            cmd = frames.decode_dp0_command(data, self.cfg.protocol)
            if isinstance(cmd, frames.Dp0Command) and not cmd.inputs & start:
                return t
        return None

    async def motion(self) -> None:
        await self.estop()
        question = (
            f"unit {self.unit}: are its wheels OFF THE GROUND (or the robot secured so it "
            f"cannot move)? Jogs at {self.speed:g} min⁻¹ follow"
        )
        if not await self.op.confirm(question):
            self._skip(["motion"], "the operator did not confirm the wheels are off the ground")
            return
        for text in ("SERVO ON ON", "START ON ON"):
            answer = self.sup.apply_text(self.unit, text)
            if answer:
                self._check("motion", text, Verdict.FAIL, answer)
                return
        await self._wait(0.2)
        for axis in (0, 1):
            if not await self._jog(axis):
                return
        for axis in (0, 1):
            if not await self._step(axis):
                return

    def _guard(self) -> Guard:
        def stop(reason: str) -> None:
            halt(self.bench, self.unit)  # at once, from the answer that showed it
            self.op.say(f"  STOPPED unit {self.unit}: {reason}")

        guard = Guard(self.sup, self.unit, self.speed, stop)
        self.sup.subscribe(guard)
        return guard

    async def _profile(
        self, trace: Trace, guard: Guard, plan: Sequence[tuple[float, float]], grace: float
    ) -> list[Phase]:
        """Run ``(speed, seconds)`` of the trace's motor one after the other; the phases
        that moved, each marked complete or not."""
        phases: list[Phase] = []
        axis = trace.axis
        for speed, seconds in plan:
            start = self.bench.now()
            guard.expect(axis, speed, start, grace)
            end = start + seconds
            while self.bench.now() < end and guard.tripped is None:
                if speed:
                    a, b = (speed, 0.0) if axis == 0 else (0.0, speed)
                    self.bench.move(self.unit, a, b)
                else:
                    self.bench.release(self.unit)
                for packet in (3, 4):  # current and pulses beside every exchange
                    self.sup.request_status(self.unit, packet)
                await self._wait(min(REFRESH_S, end - self.bench.now()))
            if speed:
                now = self.bench.now()
                done = guard.tripped is None
                phases.append(Phase(axis, speed, start - trace.t0, now - trace.t0, done))
            if guard.tripped is not None:
                break
        return phases

    async def _motion_trace(
        self, trace: Trace, plan: Sequence[tuple[float, float]], grace: float
    ) -> tuple[list[Phase], Guard]:
        guard = self._guard()
        self.collector.trace = trace
        try:
            phases = await self._profile(trace, guard, plan, grace)
            guard.expect(trace.axis, 0.0, self.bench.now(), grace)  # to rest: watched still
            self.bench.release(self.unit)
            await self.bench.wait(0.4)  # the stop, in the plot too
        finally:
            self.sup.unsubscribe(guard)
            self.collector.trace = None
            self._commands(trace)
            trace.stopped = guard.tripped
            self.result.traces.append(trace)
        return phases, guard

    def _commands(self, trace: Trace) -> None:
        """The commands as they went on the wire, as motor A/B velocities."""
        travel = self.cfg.velocity_model is VelocityModel.TRAVEL
        for t, arbitration_id, data in self.bench.wire():
            if t < trace.t0 or arbitration_id & 0x03FFFFFF != self._command_id():
                continue
            cmd = frames.decode_dp0_command(data, self.cfg.protocol)
            if isinstance(cmd, frames.Dp0Command):
                a, b = yx_to_ab(cmd.cmd_ay, cmd.cmd_bx) if travel else (cmd.cmd_ay, cmd.cmd_bx)
                trace.command.append((t - trace.t0, a, b))

    async def _jog(self, axis: int) -> bool:
        name, s = AXES[axis], self.settings
        step = f"jog {name}"
        ask = (
            f"unit {self.unit}: jog motor {name} at +{self.speed:g} then −{self.speed:g} "
            f"min⁻¹, {s.jog_s:g} s each?"
        )
        if not await self.op.confirm(ask):
            self._skip([step], "the operator declined")
            return False
        trace = Trace(step, "jog", axis, self.bench.now())
        plan = [(self.speed, s.jog_s), (0.0, max(0.3, s.jog_s / 2)), (-self.speed, s.jog_s)]
        phases, guard = await self._motion_trace(trace, plan, max(0.3, 0.6 * s.jog_s))
        checks = analysis.judge_direction(trace, phases)
        if guard.tripped is not None and all(c.verdict is Verdict.PASS for c in checks):
            checks.append(
                Check(
                    step,
                    "unexpected response",
                    Verdict.FAIL,
                    guard.tripped,
                    "",
                    "see the plot; the unit was stopped",
                )
            )
        for c in checks:
            self._check(c.step, c.name, c.verdict, c.measured, c.limit, c.fix)
        if any(c.verdict is Verdict.FAIL for c in checks) or guard.tripped is not None:
            why = f"unit stopped ({guard.tripped})" if guard.tripped else "the jog failed"
            self._skip(["motion"], f"the remaining jogs and steps: {why}")
            self.result.ended = f"{step}: {guard.tripped or 'failed'}"
            return False
        ppr = self.cfg.geometry.pulses_per_rev
        self.counted[axis] = analysis.measured_pulses_per_rev(trace, axis)
        if ppr > 0:
            c = analysis.judge_scale(trace, axis, ppr, s)
        elif axis == 1:  # nothing to hold them against but each other
            c = analysis.judge_pair(step, self.counted[0], self.counted[1], s)
        else:
            return True
        self._check(c.step, c.name, c.verdict, c.measured, c.limit, c.fix)
        return True

    async def _step(self, axis: int) -> bool:
        name, s = AXES[axis], self.settings
        step = f"step {name}"
        if not await self.op.confirm(
            f"unit {self.unit}: velocity step of motor {name} to {self.speed:g} min⁻¹ for "
            f"{s.step_s:g} s?"
        ):
            self._skip([step], "the operator declined")
            return False
        trace = Trace(step, "step", axis, self.bench.now())
        lead = 0.2
        phases, guard = await self._motion_trace(
            trace, [(0.0, lead), (self.speed, s.step_s)], max(0.3, 0.6 * s.step_s)
        )
        if guard.tripped is not None or not phases:
            self._check(
                step,
                "unexpected response",
                Verdict.FAIL,
                guard.tripped or "no step",
                "",
                "see the plot; the unit was stopped",
            )
            self._skip(["motion"], "the remaining steps: unit stopped")
            self.result.ended = f"{step}: {guard.tripped}"
            return False
        phase = phases[0]
        moved = [t for t, a, b in trace.command if t >= phase.start and (a if axis == 0 else b)]
        start = moved[0] if moved else phase.start  # the step as it went on the wire
        metrics = analysis.step_metrics(trace, axis, self.speed, start, phase.end)
        for c in analysis.judge_step(trace, metrics, s, axis):
            self._check(c.step, c.name, c.verdict, c.measured, c.limit, c.fix)
        return True


async def commission(
    bench: Bench,
    operator: Operator,
    units: Sequence[str],
    settings: Settings,
    results: dict[str, UnitResult],
) -> str | None:
    """Each unit in turn, its result in ``results`` as it goes (so an interrupted session
    still reports what it saw); why the session ended early, or None. The e-stop outside
    its rehearsal ends the session; every unit is stopped whatever happens."""
    try:
        for unit in units:
            sequence = UnitSequence(bench, operator, unit, settings)
            results[unit] = sequence.result
            await sequence.run()
    except Aborted as exc:
        for unit in units:  # the unit it interrupted, and those that never began
            result = results.setdefault(unit, UnitResult(bench.sup.units[unit].cfg))
            if unit == list(results)[-1] or not result.checks:
                result.add(Check("session", "aborted", Verdict.FAIL, str(exc)))
        return str(exc)
    finally:
        for unit in units:
            halt(bench, unit)
    return None
