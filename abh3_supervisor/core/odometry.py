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


# pose covariance (x, y, yaw variances) by what the pose rests on: the pulse counts'
# latest round (and the feedback of less than one command period since it), the velocity
# feedback integrated since the last round, or the feedback alone (no pulse counts)
POSE_VARIANCE: dict[str, tuple[float, float, float]] = {
    "pulses": (1e-6, 1e-6, 1e-5),
    "integrated": (1e-4, 1e-4, 1e-3),
    "feedback": (1e-2, 1e-2, 1e-1),
}
PLANAR_VARIANCE = 1e-9  # z, roll, pitch: a ground robot's, known to be zero
TWIST_VARIANCE = (1e-4, 1e-9, 1e-3)  # linear.x, linear.y (no side slip), angular.z


def covariance(x: float, y: float, yaw: float) -> list[float]:
    """A row-major 6×6 covariance with the (x, y, z, roll, pitch, yaw) variances on its
    diagonal; z, roll and pitch :data:`PLANAR_VARIANCE`."""
    out = [0.0] * 36
    for i, v in enumerate((x, y, PLANAR_VARIANCE, PLANAR_VARIANCE, PLANAR_VARIANCE, yaw)):
        out[7 * i] = v
    return out


@dataclass(frozen=True, slots=True)
class Sample:
    """The robot at one feedback round (every unit's DP0 reply of one command period).

    ``source`` says what the pose rests on: ``pulses`` (a round of pulse counts completed
    since the last sample: the pose is that round's, carried on to ``t`` by the feedback),
    ``integrated`` (the feedback integrated since the last round of counts) or
    ``feedback`` (no pulse counts: the feedback integrated from the start). ``positions``
    [rad] and ``velocities`` [rad/s] are the wheels' (in the robot's order), each
    positive when it rolls the robot forward (mounting sign applied).
    """

    t: float
    pose: Pose
    linear_x: float
    angular_z: float
    source: str
    positions: tuple[float, ...]
    velocities: tuple[float, ...]

    @property
    def pose_covariance(self) -> list[float]:
        return covariance(*POSE_VARIANCE[self.source])

    @property
    def twist_covariance(self) -> list[float]:
        return covariance(*TWIST_VARIANCE)


def _arc(p: Pose, linear_x: float, angular_z: float, dt: float) -> Pose:
    """``p`` moved on by a constant twist for ``dt`` (midpoint heading, as the rounds)."""
    distance, turn = linear_x * dt, angular_z * dt
    heading = p.yaw + turn / 2
    yaw = math.atan2(math.sin(p.yaw + turn), math.cos(p.yaw + turn))
    return Pose(p.x + distance * math.cos(heading), p.y + distance * math.sin(heading), yaw)


def measured_twist(
    robot: RobotConfig, geometry: Geometry | None, given: Mapping[str, Feedback]
) -> tuple[float, float]:
    """(linear.x, angular.z) of every unit's velocity feedback (``geometry``: the seed's
    one-drive conversion, to the bit)."""
    if geometry is not None:
        fbk = given[robot.units[0]]
        return yx_to_twist(fbk.vel_y, fbk.vel_x, geometry)
    speeds = {(u, axis): (f.vel_a, f.vel_b)[axis] for u, f in given.items() for axis in (0, 1)}
    return twist_of(robot, speeds)


class Odometer:
    """A robot's odometry: its pose from every wheel's pulse counts and its measured
    twist from every wheel's velocity feedback. ``geometry``: the robot is the one-drive
    robot of that unit's geometry (the seed's conversion for both, to the bit).

    Live, at the command rate (:meth:`feedback`): every round of DP0 replies (each unit's
    once) gives a :class:`Sample`: the twist from that feedback, the pose from the last
    round of pulse counts carried on by the feedback since it, or — ``counts`` False, or
    a wheel without ``pulses_per_rev`` — from the feedback alone.
    """

    def __init__(
        self, robot: RobotConfig, geometry: Geometry | None = None, *, counts: bool = True
    ) -> None:
        self.robot, self.geometry = robot, geometry
        ready = robot.odometry_ready if geometry is None else geometry.pulses_per_rev > 0
        self.odometry: RobotOdometry | None = None
        if counts and ready:
            self.odometry = (
                RobotOdometry(robot) if geometry is None else of_geometry(robot.units[0], geometry)
            )
        wheels = robot.wheels
        # a wheel's joint: rad per motor min⁻¹ [rad/s] and per pulse, mounting sign applied
        self._rad_per_min = tuple(w.sign * 2 * math.pi / 60 / w.gear_ratio for w in wheels)
        self._rad_per_pulse = tuple(
            w.sign * 2 * math.pi / (w.pulses_per_rev * w.gear_ratio) if w.pulses_per_rev else 0.0
            for w in wheels
        )
        self._feedback: dict[str, Feedback] = {}
        self._fresh: set[str] = set()
        self._counts: dict[str, tuple[float | None, tuple[int, int], tuple[int, int]]] = {}
        self._anchor: tuple[Pose, float | None] | None = None  # a new round of counts
        self._anchored = False  # a round of counts has been seen
        self._last: Sample | None = None

    @property
    def units(self) -> tuple[str, ...]:
        return self.robot.units

    @property
    def counts(self) -> bool:
        """The pose rests on pulse counts (broadcast 4)."""
        return self.odometry is not None

    @staticmethod
    def pose_covariance(source: str) -> list[float]:
        """The pose covariance that says ``source`` (a :class:`Sample`'s)."""
        return covariance(*POSE_VARIANCE[source])

    def pulses(self, unit: str, pulse_a: int, pulse_b: int, t: float | None = None) -> Pose | None:
        """``unit``'s counts, reported at ``t``; the pose when they complete a round."""
        if self.odometry is None:
            return None
        if unit in self.units:
            old = self._counts.get(unit)
            if old is None:
                unwrapped = (pulse_a, pulse_b)
            else:
                (ua, ub), (ra, rb) = old[1], old[2]
                unwrapped = (ua + _step(pulse_a, ra), ub + _step(pulse_b, rb))
            self._counts[unit] = (t, unwrapped, (pulse_a, pulse_b))
        pose = self.odometry.update(unit, pulse_a, pulse_b, t)
        if pose is not None:
            times = [c[0] for c in self._counts.values()]
            at = None if any(x is None for x in times) else min(x for x in times if x is not None)
            self._anchor = (pose, at)
        return pose

    def twist(self, feedback: Mapping[str, Feedback | None]) -> tuple[float, float]:
        """(linear.x, angular.z) the units' latest velocity feedback amounts to, every
        wheel counted; (0, 0) until every unit of the robot has given feedback."""
        given = {u: feedback.get(u) for u in self.robot.units}
        if any(f is None for f in given.values()):
            return 0.0, 0.0
        return measured_twist(self.robot, self.geometry, {u: f for u, f in given.items() if f})

    def feedback(self, unit: str, fbk: Feedback) -> Sample | None:
        """``unit``'s DP0 feedback; a :class:`Sample` when every unit of the robot has
        given feedback since the last one, else None."""
        if unit not in self.units:
            return None
        self._feedback[unit] = fbk
        self._fresh.add(unit)
        if len(self._fresh) < len(self.units):
            return None
        self._fresh = set()
        t = max(f.t for f in self._feedback.values())
        linear_x, angular_z = measured_twist(self.robot, self.geometry, self._feedback)
        velocities = tuple(
            k * (f.vel_a, f.vel_b)[w.axis]
            for w, k in zip(self.robot.wheels, self._rad_per_min, strict=True)
            for f in (self._feedback[w.unit],)
        )
        last = self._last
        if self._anchor is not None:  # a new round of counts: the pose is its
            pose, at = self._anchor
            self._anchor, self._anchored, source = None, True, "pulses"
            pose = _arc(pose, linear_x, angular_z, t - at) if at is not None else pose
        elif last is None:
            pose, source = Pose(), "feedback"
        else:  # between rounds, or without counts: the feedback, trapezoidal
            source = "integrated" if self._anchored else "feedback"
            mean = ((last.linear_x + linear_x) / 2, (last.angular_z + angular_z) / 2)
            pose = _arc(last.pose, *mean, t - last.t)
        sample = self._last = Sample(
            t, pose, linear_x, angular_z, source, self._positions(t, velocities), velocities
        )
        return sample

    def _positions(self, t: float, velocities: tuple[float, ...]) -> tuple[float, ...]:
        """Each wheel's angle [rad]: its pulse count, carried on to ``t`` by its
        feedback; without counts its feedback integrated (trapezoidal)."""
        last = self._last
        out = []
        for i, w in enumerate(self.robot.wheels):
            counted = self._counts.get(w.unit) if self.odometry is not None else None
            if counted is not None:
                at, unwrapped = counted[0], counted[1]
                since = 0.0 if at is None else t - at
                out.append(unwrapped[w.axis] * self._rad_per_pulse[i] + velocities[i] * since)
            elif last is None:
                out.append(0.0)
            else:
                mean = (last.velocities[i] + velocities[i]) / 2
                out.append(last.positions[i] + mean * (t - last.t))
        return tuple(out)


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
