"""Dead reckoning of a robot from every wheel's pulse counts (broadcast 4), and its
measured twist from every wheel's velocity feedback.

Each unit reports its two counts (pulse A, pulse B: int32 that wrap; a step is taken
modulo 2³²) in its own broadcast, at its own time. A robot's wheels may sit on several
units, so the pose advances in *rounds*: once every unit of the robot has reported since
the last step, each wheel's travel since then (its count's step × its metres per pulse,
mounting sign included) is taken, each side's travel is the mean of its wheels', and the
pose moves along the arc they make (midpoint heading). Nothing is lost or counted twice
whatever the units' rates — a count is cumulative, so a unit that reports twice within a
round only moves its own wheels' reading on — and a round waits for the slowest unit: a
unit that stops reporting (offline, broadcast 4 not in its mask) stops the pose. The
first complete round is the origin.

A one-drive robot from a unit's ``geometry`` (axis A the left wheel and B the right one,
as the seed's velocity model implies: A faster than B turns clockwise) completes a round
at every report of its unit, with the seed's own conversion (:class:`PulseOdometry`).
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
        self._latest: dict[str, tuple[int, int]] = {}  # each unit's last report
        self._base: dict[str, tuple[int, int]] | None = None  # the counts at the last step
        self._fresh: set[str] = set()  # units that reported since the last step

    def update(self, unit: str, pulse_a: int, pulse_b: int) -> Pose | None:
        """One unit's counts; the pose when they complete a round, else None."""
        if unit not in self.units:
            return None
        self._latest[unit] = (pulse_a, pulse_b)
        self._fresh.add(unit)
        if self._fresh != self.units:
            return None
        self._fresh = set()
        base, self._base = self._base, dict(self._latest)
        if base is not None:
            left, right = (self._travel(side, base) for side in (Side.LEFT, Side.RIGHT))
            self._advance(left, right)
        return self.pose

    def _travel(self, side: Side, base: Mapping[str, tuple[int, int]]) -> float:
        """The mean travel [m] of ``side``'s wheels since ``base`` (0 with no wheel)."""
        wheels = self._sides[side]
        if not wheels:
            return 0.0
        steps = [
            _step(self._latest[unit][axis], base[unit][axis]) * mpp for (unit, axis), mpp in wheels
        ]
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

    def pulses(self, unit: str, pulse_a: int, pulse_b: int) -> Pose | None:
        """``unit``'s counts; the pose when they complete a round, else None."""
        return self.odometry.update(unit, pulse_a, pulse_b)

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
