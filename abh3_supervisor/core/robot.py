"""A robot as a whole: wheels on any units' axes, its kinematics and its limits.

A robot is a differential (or skid-steer) base: every wheel is on the left or the right
side, and all the wheels of one side roll at that side's speed. Its wheels may sit on one
drive (A and B, the seed's shape), one per drive, or several per drive on several drives.
A twist (linear.x [m/s], angular.z [rad/s]) gives each side's ground speed; each wheel's
motor speed [min⁻¹] follows from its diameter, gear ratio and mounting sign. Everything
here is pure: the Supervisor applies it (docs/robots.md).

A file without ``robots:`` describes one robot per commanded unit from its ``geometry``
(axis A the left wheel and B the right one, both mounted forward, as the seed's velocity
model implies): :func:`from_geometry`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum

from abh3_supervisor.core.kinematics import Geometry

AXES = ("A", "B")


class Side(StrEnum):
    LEFT = "left"
    RIGHT = "right"


@dataclass(frozen=True, slots=True)
class Wheel:
    """One wheel: on ``unit``'s axis ``axis`` (0 = A, 1 = B), on ``side`` of the robot.

    ``sign`` is the mounting: +1 when the motor turning forward (positive min⁻¹) rolls the
    robot forward, −1 when the motor is mounted mirrored. ``gear_ratio`` is motor
    revolutions per wheel revolution (a 10:1 gearbox: 10).
    """

    unit: str
    axis: int
    side: Side
    diameter_m: float
    gear_ratio: float = 1.0
    sign: int = 1
    pulses_per_rev: float = 0.0  # encoder pulses per motor revolution; 0: unknown

    @property
    def name(self) -> str:
        return f"{self.unit}.{AXES[self.axis]}"

    @property
    def metres_per_motor_rev(self) -> float:
        return math.pi * self.diameter_m / self.gear_ratio

    def motor_speed(self, ground_mps: float) -> float:
        """The motor speed [min⁻¹] that rolls this wheel at ``ground_mps``."""
        return self.sign * ground_mps * 60.0 / self.metres_per_motor_rev

    def ground_speed(self, motor_min: float) -> float:
        """The ground speed [m/s] of this wheel when its motor turns at ``motor_min``."""
        return self.sign * motor_min * self.metres_per_motor_rev / 60.0

    def metres_per_pulse(self) -> float:
        return self.sign * self.metres_per_motor_rev / self.pulses_per_rev


@dataclass(frozen=True, slots=True)
class RobotLimits:
    """Limits in robot terms; None: not limited by the robot (the units' own still hold)."""

    linear_mps: float | None = None
    angular_radps: float | None = None
    linear_accel_mps2: float | None = None
    angular_accel_radps2: float | None = None


@dataclass(frozen=True)
class RobotConfig:
    name: str
    wheels: tuple[Wheel, ...]
    track_m: float
    limits: RobotLimits = field(default_factory=RobotLimits)
    frame_id: str = "odom"  # the odometry's frame (ROS 2 header.frame_id)
    child_frame_id: str = "base_link"  # the robot's body frame
    # made from a unit's ``geometry`` (a file without ``robots:``), named after the unit
    implicit: bool = False

    @property
    def units(self) -> tuple[str, ...]:
        """The units of the robot's wheels, in the order first named."""
        return tuple(dict.fromkeys(w.unit for w in self.wheels))

    def wheel(self, unit: str, axis: int) -> Wheel | None:
        return next((w for w in self.wheels if w.unit == unit and w.axis == axis), None)

    @property
    def odometry_ready(self) -> bool:
        """Every wheel's encoder resolution is known: odometry from pulse counts."""
        return all(w.pulses_per_rev > 0 for w in self.wheels)

    def fastest_wheel_mps(self) -> float | None:
        """The fastest a wheel rolls within the robot's limits; None: not bounded."""
        lim = self.limits
        if lim.linear_mps is None or lim.angular_radps is None:
            return None
        return lim.linear_mps + lim.angular_radps * self.track_m / 2

    def axis_limit(self, wheel: Wheel) -> float | None:
        """The speed limit [min⁻¹] of ``wheel``'s motor that follows from the robot's
        limits (the fastest wheel speed they allow); None: the robot sets none."""
        fastest = self.fastest_wheel_mps()
        return None if fastest is None else abs(wheel.motor_speed(fastest))


def wheel_axes(robot: RobotConfig | None, unit: str, motor_model: bool) -> tuple[int, ...]:
    """The axes of ``unit`` whose SERVO and START drive a wheel of ``robot``: in the motor
    model, those its wheels name; in the travel model both (SERVO/START name Y and X, each
    turning both motors); a unit of no robot, both."""
    if robot is None or not motor_model:
        return (0, 1)
    return tuple(sorted({w.axis for w in robot.wheels if w.unit == unit}))


def axis_limits(robot: RobotConfig, unit: str) -> tuple[float, float] | None:
    """``unit``'s motor A, B limits [min⁻¹] from the robot's limits (an axis that is no
    wheel of it: none, ∞); None when the robot sets no speed limit."""
    if robot.fastest_wheel_mps() is None:
        return None
    limits = [math.inf, math.inf]
    for wheel in robot.wheels:
        if wheel.unit == unit:
            limits[wheel.axis] = robot.axis_limit(wheel) or math.inf
    return limits[0], limits[1]


def side_speeds(track_m: float, linear_x: float, angular_z: float) -> tuple[float, float]:
    """(left, right) ground speeds [m/s] of a twist."""
    half = angular_z * track_m / 2
    return linear_x - half, linear_x + half


def motor_speeds(robot: RobotConfig, linear_x: float, angular_z: float) -> dict[str, list[float]]:
    """Per unit of the robot, its (A, B) motor speeds [min⁻¹] for a twist; an axis that
    carries no wheel of the robot gets 0."""
    left, right = side_speeds(robot.track_m, linear_x, angular_z)
    out = {unit: [0.0, 0.0] for unit in robot.units}
    for w in robot.wheels:
        out[w.unit][w.axis] = w.motor_speed(left if w.side is Side.LEFT else right)
    return out


def twist_of(robot: RobotConfig, speeds: Mapping[tuple[str, int], float]) -> tuple[float, float]:
    """The twist (linear.x, angular.z) that wheel motor speeds [min⁻¹] keyed by
    (unit, axis) amount to, each side the mean of its wheels; wheels not given are left
    out (a side with none counts as 0)."""
    left = _mean(w.ground_speed(speeds[w.unit, w.axis]) for w in _of(robot, speeds, Side.LEFT))
    right = _mean(w.ground_speed(speeds[w.unit, w.axis]) for w in _of(robot, speeds, Side.RIGHT))
    return (left + right) / 2, (right - left) / robot.track_m


def _of(robot: RobotConfig, given: Mapping[tuple[str, int], float], side: Side) -> list[Wheel]:
    return [w for w in robot.wheels if w.side is side and (w.unit, w.axis) in given]


def _mean(values: Iterable[float]) -> float:
    items = list(values)
    return sum(items) / len(items) if items else 0.0


def within_robot_limits(robot: RobotConfig, linear_x: float, angular_z: float) -> float:
    """The factor (≤ 1) that brings a twist within the robot's linear and angular limits,
    both scaled alike (the robot keeps its path's curvature, only slower)."""
    lim = robot.limits
    scale = 1.0
    if lim.linear_mps is not None and abs(linear_x) > lim.linear_mps:
        scale = min(scale, lim.linear_mps / abs(linear_x))
    if lim.angular_radps is not None and abs(angular_z) > lim.angular_radps:
        scale = min(scale, lim.angular_radps / abs(angular_z))
    return scale


def ramp(
    robot: RobotConfig, now: tuple[float, float], target: tuple[float, float], dt: float
) -> tuple[float, float]:
    """One step from the twist ``now`` towards ``target`` within the robot's acceleration
    limits over ``dt`` seconds. Only speeding up is bounded: slowing down (towards zero,
    not through it) is at once, at the drives' own deceleration ramps, so a stop never
    waits on the host."""
    lim = robot.limits
    return (
        _ramp_one(now[0], target[0], lim.linear_accel_mps2, dt),
        _ramp_one(now[1], target[1], lim.angular_accel_radps2, dt),
    )


def _ramp_one(now: float, target: float, accel: float | None, dt: float) -> float:
    if accel is None or (abs(target) <= abs(now) and target * now >= 0):
        return target  # unlimited, or slowing down on the same side of zero
    step = accel * max(dt, 0.0)
    return target if abs(target - now) <= step else now + math.copysign(step, target - now)


def from_geometry(unit: str, g: Geometry) -> RobotConfig:
    """The one-drive robot a unit's ``geometry`` describes (the seed's model)."""
    gear = g.rate_den / g.rate_num
    wheels = tuple(
        Wheel(unit, axis, side, g.wheel, gear, 1, g.pulses_per_rev)
        for axis, side in ((0, Side.LEFT), (1, Side.RIGHT))
    )
    return RobotConfig(unit, wheels, g.width, implicit=True)
