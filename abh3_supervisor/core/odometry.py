"""Dead reckoning of a robot from every wheel's pulse counts (broadcast 4), and its
measured twist from every wheel's velocity feedback.

Each unit reports its two counts (pulse A, pulse B: int32 that wrap; a step is taken
modulo 2³², so each wheel's count is unwrapped into an unbounded position) in its own
broadcast, at its own time and rate. A robot's wheels may sit on several units, so the
pose advances in *rounds*: once every unit of the robot has reported since the last
step, the round's time is the earliest of the units' latest reports, each wheel's
position is read at that time (interpolated linearly between the two reports of its unit
around it, so wheels sampled up to a period apart are compared at one instant), each
side's travel since the last step is the mean of its wheels' (metres per pulse, mounting
sign included), and the pose moves along the arc they make (midpoint heading). Counts are
cumulative, so nothing is lost or counted twice whatever the rates; a round waits for the
slowest unit, and a unit that stops reporting (offline, broadcast 4 not in its mask)
stops the pose. The first round at whose time every unit had reported is the origin.
Without report times (``t`` None) the latest counts are taken as they are.

A one-drive robot from a unit's ``geometry`` (axis A the left wheel and B the right one,
as the seed's velocity model implies: A faster than B turns clockwise) completes a round
at every report of its unit, with the seed's own arithmetic (:class:`PulseOdometry`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

from abh3_supervisor.config.model import Config, Role
from abh3_supervisor.core.kinematics import Geometry, yx_to_twist
from abh3_supervisor.core.robot import RobotConfig, Side, from_geometry, twist_of
from abh3_supervisor.core.state import Feedback


@dataclass(frozen=True, slots=True)
class Pose:
    x: float = 0.0  # [m]
    y: float = 0.0  # [m]
    yaw: float = 0.0  # [rad], counter-clockwise, in (−π, π]


def _step(new: int, old: int) -> int:
    """Signed difference of two int32 counters, across a wrap."""
    return (new - old + (1 << 31)) % (1 << 32) - (1 << 31)


Position = int | float  # an unwrapped count; a float once interpolated


class RobotOdometry:
    """Integrates a robot's pose from its units' (pulse A, pulse B) readings, in rounds
    (see the module's docstring); starts at the origin.

    ``metres_per_pulse`` overrides a wheel's own (keyed by (unit, axis)), so a one-drive
    robot from a ``geometry`` keeps the seed's arithmetic to the bit.
    """

    def __init__(
        self,
        robot: RobotConfig,
        metres_per_pulse: Mapping[tuple[str, int], float] | None = None,
    ) -> None:
        if not robot.odometry_ready:
            raise ValueError(f"odometry of robot {robot.name} needs every wheel's pulses_per_rev")
        given = metres_per_pulse or {}
        self.robot = robot
        self.track = robot.track_m
        self.units = frozenset(robot.units)
        # per side: ((unit, axis), metres per pulse, sign included) of each wheel
        self._sides = {
            side: tuple(
                ((w.unit, w.axis), given.get((w.unit, w.axis), w.metres_per_pulse()))
                for w in robot.wheels
                if w.side is side
            )
            for side in Side
        }
        self.pose = Pose()
        self._raw: dict[str, tuple[int, int]] = {}  # each unit's last counts, as sent
        # per unit: (time, unwrapped (A, B)) of its reports from just before the last round
        self._reports: dict[str, list[tuple[float | None, tuple[int, int]]]] = {}
        self._base: dict[tuple[str, int], Position] | None = None  # at the last step
        self._fresh: set[str] = set()  # units that reported since the last step

    def update(self, unit: str, pulse_a: int, pulse_b: int, t: float | None = None) -> Pose | None:
        """One unit's counts, reported at ``t`` [s]; the pose when they complete a round,
        else None."""
        if unit not in self.units:
            return None
        reports = self._reports.setdefault(unit, [])
        raw = self._raw.get(unit)
        if raw is None:
            position = (pulse_a, pulse_b)
        else:
            a, b = reports[-1][1]
            position = (a + _step(pulse_a, raw[0]), b + _step(pulse_b, raw[1]))
        self._raw[unit] = (pulse_a, pulse_b)
        reports.append((t, position))
        self._fresh.add(unit)
        at = self._round_time()
        if not self._complete(at):
            self._prune(t)
            return None
        self._fresh = set()
        positions = {(u, axis): self._position(u, axis, at) for u in self.units for axis in (0, 1)}
        base, self._base = self._base, positions
        if base is not None:
            left, right = (self._travel(side, base, positions) for side in (Side.LEFT, Side.RIGHT))
            self._advance(left, right)
        return self.pose

    def _complete(self, at: float | None) -> bool:
        """Every unit reported anew — and, for the origin, each had reported by ``at``."""
        if self._fresh != self.units:
            return False
        return at is None or all(r[0][0] is None or r[0][0] <= at for r in self._reports.values())

    def _round_time(self) -> float | None:
        """The earliest of the units' latest report times; None if a report has none."""
        latest = [r[-1][0] for r in self._reports.values()]
        return None if any(t is None for t in latest) else min(t for t in latest if t is not None)

    def _prune(self, now: float | None) -> None:
        """Drop the reports no round can need, so a silent unit costs no memory: the next
        round's time is no earlier than a fresh unit's latest report, nor than ``now``
        when a unit has yet to report again."""
        fresh = [r[-1][0] for u, r in self._reports.items() if u in self._fresh]
        if len(self._fresh) < len(self.units):
            fresh.append(now)
        known = [t for t in fresh if t is not None]
        if len(known) < len(fresh):  # without times only the latest counts are read
            for reports in self._reports.values():
                del reports[:-1]
            return
        floor = min(known)
        for reports in self._reports.values():
            keep = max(
                (i for i, (t, _) in enumerate(reports) if t is not None and t <= floor), default=0
            )
            del reports[:keep]

    def _position(self, unit: str, axis: int, at: float | None) -> Position:
        """``unit``'s ``axis`` position at ``at``: between the reports around it, the last
        one when ``at`` is later (or None); every unit has one at or before ``at``. Reports
        before that one are dropped afterwards: rounds only move on."""
        reports = self._reports[unit]
        t1, p1 = reports[-1]
        if at is None or t1 is None or t1 <= at:
            del reports[:-1]
            return p1[axis]
        i = max(i for i, (t, _) in enumerate(reports) if t is not None and t <= at)
        del reports[:i]
        (t0, p0), (t1, p1) = reports[0], reports[1]
        assert t0 is not None and t1 is not None
        return p0[axis] + (p1[axis] - p0[axis]) * (at - t0) / (t1 - t0)

    def _travel(
        self,
        side: Side,
        before: Mapping[tuple[str, int], Position],
        now: Mapping[tuple[str, int], Position],
    ) -> float:
        """The mean travel [m] of ``side``'s wheels from ``before`` to ``now`` (0 with no
        wheel)."""
        wheels = self._sides[side]
        if not wheels:
            return 0.0
        steps = [(now[key] - before[key]) * mpp for key, mpp in wheels]
        return sum(steps) / len(steps)

    def _advance(self, left: float, right: float) -> None:
        distance, turn = (left + right) / 2, (right - left) / self.track
        p = self.pose
        heading = p.yaw + turn / 2  # midpoint: exact for arcs to second order
        yaw = math.atan2(math.sin(p.yaw + turn), math.cos(p.yaw + turn))
        self.pose = Pose(
            p.x + distance * math.cos(heading), p.y + distance * math.sin(heading), yaw
        )


def _geometry_mpp(geometry: Geometry) -> float:
    if geometry.pulses_per_rev <= 0:
        raise ValueError("odometry needs geometry.pulses_per_rev")
    return geometry.metres_per_motor_rev / geometry.pulses_per_rev


def of_geometry(unit: str, geometry: Geometry) -> RobotOdometry:
    """The odometry of the one-drive robot a unit's ``geometry`` describes (the seed's)."""
    mpp = _geometry_mpp(geometry)
    return RobotOdometry(from_geometry(unit, geometry), {(unit, 0): mpp, (unit, 1): mpp})


class PulseOdometry:
    """One drive's odometry from its ``geometry``: (pulse A, pulse B) readings in."""

    def __init__(self, geometry: Geometry) -> None:
        self.metres_per_pulse = _geometry_mpp(geometry)
        self.width = geometry.width
        self._robot = of_geometry("", geometry)

    @property
    def pose(self) -> Pose:
        return self._robot.pose

    def update(self, pulse_a: int, pulse_b: int) -> Pose:
        pose = self._robot.update("", pulse_a, pulse_b)
        assert pose is not None  # one unit: every report completes a round
        return pose


class Odometer:
    """A robot's odometry: its pose from every wheel's pulse counts and its measured
    twist from every wheel's velocity feedback. ``geometry``: the robot is the one-drive
    robot of that unit's geometry (the seed's conversion for both, to the bit)."""

    def __init__(self, robot: RobotConfig, geometry: Geometry | None = None) -> None:
        self.robot, self.geometry = robot, geometry
        self.odometry = (
            RobotOdometry(robot) if geometry is None else of_geometry(robot.units[0], geometry)
        )

    @property
    def units(self) -> tuple[str, ...]:
        return self.robot.units

    def pulses(self, unit: str, pulse_a: int, pulse_b: int, t: float | None = None) -> Pose | None:
        """``unit``'s counts, reported at ``t``; the pose when they complete a round."""
        return self.odometry.update(unit, pulse_a, pulse_b, t)

    def twist(self, feedback: Mapping[str, Feedback | None]) -> tuple[float, float]:
        """(linear.x, angular.z) the units' latest velocity feedback amounts to, every
        wheel counted; (0, 0) until every unit of the robot has given feedback."""
        given = {u: feedback.get(u) for u in self.robot.units}
        if any(f is None for f in given.values()):
            return 0.0, 0.0
        if self.geometry is not None:
            fbk = given[self.robot.units[0]]
            assert fbk is not None
            return yx_to_twist(fbk.vel_y, fbk.vel_x, self.geometry)
        speeds = {
            (u, axis): (f.vel_a, f.vel_b)[axis]
            for u, f in given.items()
            if f is not None
            for axis in (0, 1)
        }
        return twist_of(self.robot, speeds)


def odometers(config: Config) -> Iterator[Odometer]:
    """Every robot of ``config`` with odometry: a declared robot whose every wheel's
    pulses_per_rev is known, a one-drive robot (also of a monitor unit) whose geometry
    gives pulses_per_rev. A one-drive robot is named after its unit."""
    for robot in config.robots.values():
        if robot.implicit:
            geometry = config.units[robot.units[0]].geometry
            if geometry.pulses_per_rev > 0:
                yield Odometer(robot, geometry)
        elif robot.odometry_ready:
            yield Odometer(robot)
    for name, unit in config.units.items():
        if unit.role is Role.MONITOR and unit.geometry.pulses_per_rev > 0:
            yield Odometer(from_geometry(name, unit.geometry), unit.geometry)


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)
