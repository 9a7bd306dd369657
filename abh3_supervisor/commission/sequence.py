"""The commissioning sequence of one unit: identity and settings (:mod:`.identity`),
e-stop rehearsal, direction and wiring per motor, step response per motor, summary.

It runs against a :class:`~.unit.Bench` — the clock, motion through the input arbitration
(a source of its own whose commands lapse unless repeated, so a stalled sequence stops the
jog), the wire's frames and the parameter channel — and an :class:`~.unit.Operator`
(questions, the e-stop key). The terminal client provides both on a live runtime; tests
provide them on a fake clock. A :class:`~.guard.Guard` watches every answer while a unit
moves and stops it at once with the safe word; the e-stop (``Supervisor.estop``) ends the
session.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping, Sequence

from abh3_supervisor.commission import analysis
from abh3_supervisor.commission.analysis import Phase
from abh3_supervisor.commission.guard import Guard
from abh3_supervisor.commission.identity import IdentitySteps
from abh3_supervisor.commission.model import AXES, Check, Settings, Trace, Verdict
from abh3_supervisor.commission.robot import RobotResult, RobotSequence
from abh3_supervisor.commission.unit import Aborted, Bench, Operator, UnitResult, halt
from abh3_supervisor.config.model import VelocityModel
from abh3_supervisor.core.kinematics import yx_to_ab
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import frames, ids

REFRESH_S = 0.05  # the sequence repeats its command this often (the source lapses at 0.3 s)
MIN_WAIT_S = 0.001
SOURCE_TIMEOUT_S = 0.3


class UnitSequence(IdentitySteps):
    """Identity (:class:`~.identity.IdentitySteps`), then the e-stop rehearsal, the jogs
    and the steps."""

    async def run(self) -> UnitResult:
        self.sup.subscribe(self.collector)
        try:
            if await self.identity():
                await self.motion()
        finally:
            self.sup.unsubscribe(self.collector)
            halt(self.bench, self.unit)
        return self.result

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
        slow = self.settings.too_slow(self.unit, self.cfg.limits.velocity)
        if slow is not None:  # the client refuses it first; a bench given it moves nothing
            self._check("motion", "jog speed", Verdict.FAIL, f"{self.speed:g} min⁻¹", "", slow)
            return
        question = (
            f"unit {self.unit}: are its wheels OFF THE GROUND (or the robot secured so it "
            f"cannot move)? Jogs at {self.speed:g} min⁻¹ follow"
        )
        if not await self.op.confirm(question):
            self._skip(["motion"], "the operator did not confirm the wheels are off the ground")
            return
        # velocity commands need the torque bits off: `control: current` sets them at start
        for text in ("TORQUE OFF OFF", "SERVO ON ON", "START ON ON"):
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
            while (now := self.bench.now()) < end:
                guard.tick(now)  # a drive gone silent: stopped, and nothing more commanded
                if guard.tripped is not None:
                    break
                if speed:
                    a, b = (speed, 0.0) if axis == 0 else (0.0, speed)
                    self.bench.move(self.unit, a, b)
                else:
                    self.bench.release(self.unit)
                for packet in (3, 4):  # current and pulses beside every exchange
                    self.sup.request_status(self.unit, packet)
                # awake by the guard's deadline: a silence is noticed when it begins to count
                wake = min(REFRESH_S, end - now, guard.deadline() - now)
                await self._wait(max(wake, MIN_WAIT_S))
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
        checks = (
            [analysis.communication_lost(step, guard.tripped or "")]
            if guard.silence is not None  # no answers to judge: the link, not the motor
            else analysis.judge_direction(trace, phases)
        )
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
        ppr, keys = self._scale_keys(axis)
        self.counted[axis] = analysis.measured_pulses_per_rev(trace, axis)
        if ppr > 0:
            c = analysis.judge_scale(trace, axis, ppr, s, keys)
        elif axis == 1:  # nothing to hold them against but each other
            c = analysis.judge_pair(step, self.counted[0], self.counted[1], s, keys[0])
        else:
            return True
        self._check(c.step, c.name, c.verdict, c.measured, c.limit, c.fix)
        return True

    def _scale_keys(self, axis: int) -> tuple[float, tuple[str, str, str]]:
        """The pulses per motor revolution the file gives this motor, and where it and the
        gear ratio are set: the wheel of a declared robot (a robot's unit has no
        ``geometry``), else the unit's geometry."""
        robot = self.sup.config.robot_of(self.unit)
        wheel = robot.wheel(self.unit, axis) if robot is not None else None
        if robot is None or robot.implicit or wheel is None:
            return self.cfg.geometry.pulses_per_rev, analysis.GEOMETRY_KEYS
        at = f"robots.{robot.name}.wheels[{robot.wheels.index(wheel)}]"
        return wheel.pulses_per_rev, (
            f"pulses_per_rev in robots: {robot.name} (or its wheel's)",
            f"pulses_per_rev: {{}} for {at} ({wheel.name}), or robots.{robot.name}."
            "pulses_per_rev for every wheel,",
            f"gear_ratio for {at} (or robots.{robot.name}.gear_ratio)",
        )

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
            c = (
                analysis.communication_lost(step, guard.tripped or "")
                if guard.silence is not None
                else Check(
                    step,
                    "unexpected response",
                    Verdict.FAIL,
                    guard.tripped or "no step",
                    "",
                    "see the plot; the unit was stopped",
                )
            )
            self._check(c.step, c.name, c.verdict, c.measured, c.limit, c.fix)
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
    startups: Mapping[str, Sequence[str]] | None = None,
    robots: dict[str, RobotResult] | None = None,
) -> str | None:
    """Each unit in turn, its result in ``results`` as it goes (so an interrupted session
    still reports what it saw); why the session ended early, or None. The e-stop outside
    its rehearsal ends the session; every unit is stopped whatever happens. ``startups``:
    the file's ``startup:`` per unit, not run; one that sets a unit moving refuses it.
    Given ``robots``, the robot step follows (:mod:`.robot`) for each robot of the file
    whose units are all commissioned here, its result there."""
    try:
        for unit in units:
            startup = (startups or {}).get(unit, ())
            sequence = UnitSequence(bench, operator, unit, settings, startup)
            results[unit] = sequence.result
            await sequence.run()
        if robots is not None:
            await _robots(bench, operator, units, settings, results, robots)
    except Aborted as exc:
        _ended(bench, units, results, "aborted", str(exc), robots)
        return str(exc)
    except asyncio.CancelledError:  # Ctrl-C, a signal, the runtime's fatal error
        _ended(bench, units, results, "interrupted", "the session was stopped", robots)
        raise
    finally:
        for unit in units:
            halt(bench, unit)
    return None


async def _robots(
    bench: Bench,
    operator: Operator,
    units: Sequence[str],
    settings: Settings,
    results: Mapping[str, UnitResult],
    robots: dict[str, RobotResult],
) -> None:
    for robot in bench.sup.config.robots.values():
        if not set(robot.units) & set(units):
            continue  # none of its units commissioned here: not asked for
        missing = [u for u in robot.units if u not in units]
        failed = [u for u in robot.units if u in units and not _moved_well(results[u])]
        sequence = RobotSequence(bench, operator, robot, settings)
        robots[robot.name] = sequence.result
        if missing or failed:
            why = (
                f"{', '.join(missing)} not commissioned"
                if missing
                else f"unit {', '.join(failed)} did not pass its own steps"
            )
            sequence.result.checks.append(Check("robot", "not run", Verdict.SKIPPED, why))
            sequence.result.ended = f"not run: {why}"
            sequence.result.not_run = True
            operator.say(f"robot {robot.name}: not run: {why}")
            continue
        await sequence.run()


def _moved_well(result: UnitResult) -> bool:
    """Every motion step ran and none failed."""
    verdicts = {c.verdict for c in result.checks}
    return Verdict.FAIL not in verdicts and Verdict.SKIPPED not in verdicts


def _ended(
    bench: Bench,
    units: Sequence[str],
    results: dict[str, UnitResult],
    name: str,
    why: str,
    robots: dict[str, RobotResult] | None = None,
) -> None:
    """The session ended early: the unit (or the robot) it interrupted fails (it was not
    fully checked, whatever passed before), and so does each unit that never began."""
    robot = next(reversed(robots), None) if robots else None
    if robots and robot is not None:
        robots[robot].checks.append(Check("session", name, Verdict.FAIL, f"{why} during its step"))
        robots[robot].ended = robots[robot].ended or why
        return  # every unit's own steps were over
    current = next(reversed(results), None)
    for unit in units:
        result = results.get(unit)
        if result is None:
            result = results[unit] = UnitResult(bench.sup.units[unit].cfg)
            before = f"not commissioned: {why} before it began"
            result.add(Check("session", name, Verdict.FAIL, before))
            result.ended = before
        elif unit == current:
            result.add(Check("session", name, Verdict.FAIL, f"{why} during its sequence"))
            result.ended = result.ended or why
