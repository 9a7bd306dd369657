"""The robot step, after every unit's own steps passed: each wheel alone at creep speed —
which wheel turned, which way it rolls the robot — then a short straight run and a turn on
the spot against a measured distance and angle (the wheels' diameter and the track).

The answers come from the operator on a terminal (one key each; typed measurements), or in
simulation from the simulated robot (:class:`RobotView`: no questions). Every motor stays
within its unit's jog speed; the commands lapse as the units' do (the same input source).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from abh3_supervisor.commission import wheels
from abh3_supervisor.commission.model import Check, Settings, Verdict, overall
from abh3_supervisor.commission.unit import Aborted, Bench, Operator, RobotView, halt
from abh3_supervisor.commission.wheels import STEP, Place, Seen
from abh3_supervisor.core.robot import RobotConfig, Side, Wheel
from abh3_supervisor.core.supervisor import SupervisorEvent
from abh3_supervisor.scheduler.core import FeedbackEvent

REFRESH_S = 0.05
SETTLE_S = 0.5  # after a move, until the wheels stand
TURNED = 0.2  # of the travel asked: a wheel that rolled less did not turn
MOTOR_TURNED = 0.5  # of the speed asked, by its drive's feedback: the motor turned
RUN_S = 1.5  # the straight run and the turn, each


@dataclass
class RobotResult:
    robot: RobotConfig
    checks: list[Check] = field(default_factory=list)
    seen: dict[Place, Seen] = field(default_factory=dict)
    source: str = ""  # who told which wheel turned: "the simulated robot", "the operator"
    # the other robots' wheel places a wheel of this one may have turned, by name
    elsewhere: dict[Place, str] = field(default_factory=dict)
    ended: str | None = None
    not_run: bool = False  # never began: a unit of it failed or was not commissioned

    @property
    def verdict(self) -> Verdict:
        return Verdict.SKIPPED if self.not_run else overall(self.checks)


class Odometer:
    """The metres each wheel rolled by the drives' DP0 feedback and the file's wheels
    (trapezoids between answers): what the file's geometry expects of a run."""

    def __init__(self, bench: Bench, robot: RobotConfig) -> None:
        self.sup, self.robot = bench.sup, robot
        self.travel = {(w.unit, w.axis): 0.0 for w in robot.wheels}
        self._last: dict[str, tuple[float, float, float]] = {}

    def __call__(self, event: SupervisorEvent) -> None:
        if not isinstance(event, FeedbackEvent) or event.unit not in self.robot.units:
            return
        fb = self.sup.units[event.unit].feedback
        if fb is None or fb.t != event.t:
            return
        before = self._last.get(event.unit)
        self._last[event.unit] = (fb.t, fb.vel_a, fb.vel_b)
        if before is None:
            return
        dt = fb.t - before[0]
        for axis, now in enumerate((fb.vel_a, fb.vel_b)):
            w = self.robot.wheel(event.unit, axis)
            if w is not None:
                mean = (before[1 + axis] + now) / 2
                self.travel[w.unit, w.axis] += w.ground_speed(mean) * dt

    def sides(self) -> tuple[float, float]:
        """(left, right): the mean metres of each side's wheels."""
        out = []
        for side in (Side.LEFT, Side.RIGHT):
            rolled = [self.travel[w.unit, w.axis] for w in self.robot.wheels if w.side is side]
            out.append(sum(rolled) / len(rolled) if rolled else 0.0)
        return out[0], out[1]


class RobotSequence:
    def __init__(
        self, bench: Bench, operator: Operator, robot: RobotConfig, settings: Settings
    ) -> None:
        self.bench, self.op, self.robot, self.settings = bench, operator, robot, settings
        self.sup = bench.sup
        self.result = RobotResult(robot)
        self.view: RobotView | None = bench.sim_robot(robot.name)
        self.names = wheels.places(robot)
        # the other simulated robots: a drive may sit on one of their wheels (swapped)
        self.others: dict[str, RobotView] = {}
        self.other_robots: list[RobotConfig] = []
        for other in self.sup.config.robots.values():
            view = bench.sim_robot(other.name)
            if other.name != robot.name and view is not None and self.view is not None:
                self.others[other.name] = view
                self.other_robots.append(other)
        self.result.elsewhere = wheels.elsewhere(robot, self.other_robots)
        self.peak: dict[Place, float] = {}  # each motor's fastest in the move, by feedback
        self.jog = {
            u: settings.jog_speed(self.sup.units[u].cfg.limits.velocity) for u in robot.units
        }
        # the ground speed at which no wheel's motor turns faster than its unit's jog
        self.creep = min(self.jog[w.unit] * w.metres_per_motor_rev / 60 for w in robot.wheels)

    def _check(self, check: Check) -> None:
        self.result.checks.append(check)
        mark = {"pass": "ok", "warn": "WARN", "fail": "FAIL", "not run": "--"}[check.verdict.value]
        fix = f" → {check.fix}" if check.fix and check.verdict is not Verdict.PASS else ""
        self.op.say(f"  [{mark:>4}] robot {self.robot.name}: {check.name}: {check.measured}{fix}")

    def _skip(self, what: str, why: str) -> None:
        self._check(Check(STEP, what, Verdict.SKIPPED, why))
        self.result.ended = self.result.ended or why

    async def _wait(self, seconds: float) -> None:
        await self.bench.wait(seconds)
        if self.sup.estop:
            raise Aborted("e-stop pressed")

    async def run(self) -> RobotResult:
        try:
            await self._run()
        finally:
            for unit in self.robot.units:
                halt(self.bench, unit)
        return self.result

    async def _energise(self) -> bool:
        """SERVO and START on for every unit of the robot (each unit's steps ended with
        them off), velocity commands (the torque bits off)."""
        for unit in self.robot.units:
            for text in ("TORQUE OFF OFF", "SERVO ON ON", "START ON ON"):
                answer = self.sup.apply_text(unit, text)
                if answer:
                    self._check(Check(STEP, f"{unit}: {text}", Verdict.FAIL, answer))
                    return False
        await self._wait(0.2)
        return True

    async def _run(self) -> None:
        r, asking = self.robot, self.view is None
        self.result.source = "the operator" if asking else "the simulated robot"
        self.op.say(
            f"robot {r.name}: {len(r.wheels)} wheels on {', '.join(r.units)}, track "
            f"{r.track_m:g} m; which wheel turns and which way: from {self.result.source}"
        )
        if asking and not self.op.interactive:
            self._skip("wheels", "no terminal to ask which wheel turned (and no simulated robot)")
            return
        if not await self.op.confirm(
            f"robot {r.name}: turn each wheel alone, forward at {self.creep:.3f} m/s for "
            f"{self.settings.jog_s:g} s (wheels off the ground, or room to roll)?"
        ):
            self._skip("wheels", "the operator declined")
            return
        if not await self._energise():
            return
        for w in r.wheels:
            self.result.seen[w.unit, w.axis] = await self._one_wheel(w)
        found = wheels.judge_wheels(r, self.result.seen, self.other_robots)
        for c in found:
            self._check(c)
        if any(c.verdict is Verdict.FAIL for c in found):
            self._skip("straight run and turn", "fix the wheels above first")
            return
        await self._geometry()

    async def _move(self, send: Callable[[], None], seconds: float) -> None:
        """``send`` the command every refresh for ``seconds``, then let go: at rest. The
        arbitration gives a robot one owner: a unit's command zeroes the robot's other
        units, a twist drives them all."""
        end = self.bench.now() + seconds
        while (now := self.bench.now()) < end:
            send()
            self._watch()
            await self._wait(max(min(REFRESH_S, end - now), 0.001))
        for unit in self.robot.units:
            self.bench.release(unit)
        await self._wait(SETTLE_S)

    def _wheel(self, w: Wheel) -> Callable[[], None]:
        """Only ``w``'s motor, forward at creep speed (as the file says the wheel is)."""
        speed = w.motor_speed(self.creep)
        a, b = (speed, 0.0) if w.axis == 0 else (0.0, speed)
        return lambda: self.bench.move(w.unit, a, b)

    def _twist(self, linear_x: float, angular_z: float) -> Callable[[], None]:
        """The whole robot, as a twist decides its wheels (core/robot.py)."""
        unit = self.robot.units[0]
        return lambda: self.bench.twist(unit, linear_x, angular_z)

    def _watch(self) -> None:
        """A motor beyond twice its jog speed: every unit of the robot stopped at once.
        Each motor's fastest by its drive's feedback is noted (:attr:`peak`)."""
        for unit in self.robot.units:
            fb = self.sup.units[unit].feedback
            if fb is None:
                continue
            for axis, vel in enumerate((fb.vel_a, fb.vel_b)):
                if abs(vel) > abs(self.peak.get((unit, axis), 0.0)):
                    self.peak[unit, axis] = vel
            if max(abs(fb.vel_a), abs(fb.vel_b)) > 2 * self.jog[unit]:
                for u in self.robot.units:
                    halt(self.bench, u)
                raise Aborted(f"robot {self.robot.name}: unit {unit} beyond twice its jog speed")

    async def _one_wheel(self, w: Wheel) -> Seen:
        place = (w.unit, w.axis)
        before = self._travel()
        self.peak.clear()
        await self._move(self._wheel(w), self.settings.jog_s)
        # the drive's own word on its motor: turning while no wheel does says where it is
        asked, fastest = w.motor_speed(self.creep), self.peak.get(place, 0.0)
        motor = (
            fastest if fastest * asked > 0 and abs(fastest) >= MOTOR_TURNED * abs(asked) else None
        )
        if self.view is not None:
            seen = _turned(before, self._travel(), self.creep * self.settings.jog_s)
        else:
            seen = await self._ask(w, place)
        return dataclasses.replace(seen, motor_min=motor)

    def _travel(self) -> dict[Place, float]:
        """Every simulated wheel's travel: this robot's, then the others'."""
        views = [v for v in (self.view, *self.others.values()) if v is not None]
        return {p: d for v in views for p, d in v.travel.items()}

    async def _ask(self, w: Wheel, place: Place) -> Seen:
        keys = {str(i + 1): p for i, p in enumerate(self.names)}
        options = [(k, self.names[p]) for k, p in keys.items()] + [("0", "none")]
        key = await self.op.choose(
            f"robot {self.robot.name}: {w.name} was asked to roll the "
            f"{self.names[place]} wheel forward — which wheel turned?",
            options,
        )
        if key is None or key == "0":
            return Seen(None, 0)
        way = await self.op.choose(
            f"robot {self.robot.name}: the {self.names[keys[key]]} wheel — which way would "
            "it roll the robot?",
            [("f", "forward"), ("b", "backward"), ("0", "neither")],
        )
        return Seen(keys[key], {"f": 1, "b": -1}.get(way or "0", 0))

    async def _geometry(self) -> None:
        r, run_s = self.robot, RUN_S
        ahead = self.creep * run_s
        if not await self.op.confirm(
            f"robot {r.name}: ON THE GROUND with {ahead:.2f} m clear ahead? A straight run "
            f"of about {ahead:.2f} m and a turn on the spot follow, to measure the "
            "wheels' diameter and the track"
        ):
            self._skip(
                "straight run and turn", "the operator declined: diameter and track unchecked"
            )
            return
        odo = Odometer(self.bench, r)
        self.sup.subscribe(odo)
        try:
            ratio = await self._straight(odo, run_s)
            await self._turn(odo, run_s, ratio)
        finally:
            self.sup.unsubscribe(odo)

    async def _straight(self, odo: Odometer, run_s: float) -> tuple[float, float]:
        """Each side's diameters' ratio found (true/file's); 1 where not measured."""
        start = self.view.distance if self.view is not None else 0.0
        heading = self.view.heading if self.view is not None else 0.0
        before = odo.sides()
        await self._move(self._twist(self.creep, 0.0), run_s)
        after = odo.sides()
        sides = (after[0] - before[0], after[1] - before[1])
        expected = sum(sides) / 2
        drift: float | None = None
        if self.view is not None:
            measured: float | None = self.view.distance - start
            drift = self.view.heading - heading
        else:
            measured = await self.op.measure(
                f"robot {self.robot.name}: how far did it go, in metres (the file's wheels "
                f"say {expected:.3f})? Enter skips"
            )
        if measured is None:
            self._skip("wheel diameter (straight run)", "not measured: the operator skipped it")
            return 1.0, 1.0
        curved = None if drift is None else wheels.judge_sides(self.robot, sides, measured, drift)
        if curved is not None:
            self._check(curved)
            half = drift * self.robot.track_m / 2 if drift is not None else 0.0
            return (
                (measured - half) / sides[0] if sides[0] else 1.0,
                (measured + half) / sides[1] if sides[1] else 1.0,
            )
        check = wheels.judge_diameter(self.robot, expected, measured)
        self._check(check)
        ratio = measured / expected if expected and check.verdict is Verdict.FAIL else 1.0
        return ratio, ratio

    async def _turn(self, odo: Odometer, run_s: float, ratio: tuple[float, float]) -> None:
        start = self.view.heading if self.view is not None else 0.0
        before = odo.sides()
        await self._move(self._twist(0.0, 2 * self.creep / self.robot.track_m), run_s)
        after = odo.sides()
        left, right = (k * (a - b) for k, a, b in zip(ratio, after, before, strict=True))
        expected = (right - left) / self.robot.track_m
        if self.view is not None:
            measured: float | None = self.view.heading - start
        else:
            degrees = await self.op.measure(
                f"robot {self.robot.name}: how far did it turn, in degrees counter-clockwise "
                f"(the file's track says {math.degrees(expected):.0f})? Enter skips"
            )
            measured = None if degrees is None else math.radians(degrees)
        if measured is None:
            self._skip("track (turn on the spot)", "not measured: the operator skipped it")
            return
        self._check(wheels.judge_track(self.robot, expected, measured))


def _turned(before: Mapping[Place, float], after: Mapping[Place, float], asked: float) -> Seen:
    """The wheel that rolled most, and which way; none when none rolled a fifth of it."""
    moved = {p: after[p] - before.get(p, 0.0) for p in after}
    place = max(moved, key=lambda p: abs(moved[p]), default=None)
    if place is None or abs(moved[place]) < TURNED * asked:
        return Seen(None, 0)
    return Seen(place, 1 if moved[place] > 0 else -1)
