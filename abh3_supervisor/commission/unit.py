"""What every step of a unit's commissioning works with: the :class:`Bench` and the
:class:`Operator` it is given (the terminal client provides both on a live runtime, tests
on a fake clock), the unit's result as it grows, the collector that fills the open trace
from the supervisor's events, :func:`halt`, and the helpers the steps share."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from abh3_supervisor.commission.model import Check, Settings, Trace, Verdict, overall
from abh3_supervisor.config.model import Role, UnitConfig
from abh3_supervisor.core.supervisor import Supervisor, SupervisorEvent
from abh3_supervisor.core.verify import Verification
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.core import FeedbackEvent, StatusEvent

log = logging.getLogger(__name__)


class Aborted(Exception):
    """The e-stop was pressed outside its rehearsal: the session ends, drives stopped."""


class RobotView(Protocol):
    """A simulated robot's true motion (simulator/robot.py): what the robot step asks it."""

    travel: dict[tuple[str, int], float]  # metres each wheel place rolled, forward positive
    distance: float  # the centre's path length [m]
    heading: float  # [rad], counter-clockwise positive


class Bench(Protocol):
    sup: Supervisor

    def now(self) -> float: ...
    async def wait(self, seconds: float) -> None: ...
    def move(self, unit: str, a: float, b: float) -> None:
        """Motors A and B [min⁻¹], as the commissioning input's command (arbitrated)."""

    def release(self, unit: str) -> None:
        """The commissioning input lets go of ``unit``: zero at once."""

    def twist(self, unit: str, linear_x: float, angular_z: float) -> None:
        """A twist [m/s, rad/s] for ``unit``'s robot, as the commissioning input's."""

    def wire(self) -> Sequence[tuple[float, int, bytes]]:
        """Every frame the host sent, (time, identifier, data), in order."""

    async def identity(self, unit: str) -> str: ...
    async def read_param(self, unit: str, address: int) -> int: ...
    async def verification(self, unit: str) -> Verification: ...
    def sim_robot(self, name: str) -> RobotView | None:
        """The simulated robot ``name`` (the robot step asks it, not the operator); None
        on real drives."""


class Operator(Protocol):
    # a person at a terminal answers choose() and measure(); without one they return None
    interactive: bool

    def say(self, text: str) -> None: ...
    async def confirm(self, question: str) -> bool: ...
    async def choose(self, question: str, options: Sequence[tuple[str, str]]) -> str | None:
        """One key of ``options`` ((key, meaning), …); None: no answer to be had."""

    async def measure(self, question: str) -> float | None:
        """A number typed in (Enter alone: None, skipped)."""

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
        return overall(self.checks)

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


class UnitSteps:
    """A unit's state, result and collector, and the helpers of every step."""

    def __init__(
        self,
        bench: Bench,
        operator: Operator,
        unit: str,
        settings: Settings,
        startup: Sequence[str] = (),
    ) -> None:
        self.bench, self.op, self.settings = bench, operator, settings
        self.startup = startup  # the file's, which commissioning does not run
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
