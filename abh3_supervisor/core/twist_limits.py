"""The fastest twist a robot may be asked, for what drives it by hand (the TUI's arrows,
the keyboard and joystick plugins): going straight, and turning on the spot.

It is the twist at which the first of the robot's bounds binds — its own ``limits``
(linear_mps, angular_radps, and each wheel's axis limit that follows from them), each of
its units' ``limits.velocity`` on the fields the drive reads (its velocity model) and the
wire's range — the same bounds the Supervisor's one clamp for the robot applies
(core/robot_motion.py), so a key never asks for more than the robot will do.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from abh3_supervisor.config.model import UnitConfig, VelocityModel
from abh3_supervisor.core.kinematics import ab_to_yx
from abh3_supervisor.core.robot import RobotConfig, motor_speeds
from abh3_supervisor.protocol.scaling import VELOCITY


def fastest_twist(robot: RobotConfig, units: Mapping[str, UnitConfig]) -> tuple[float, float]:
    """(linear.x [m/s] going straight, angular.z [rad/s] turning on the spot)."""
    lim = robot.limits
    straight = headroom(robot, units, 1.0, 0.0)
    turning = headroom(robot, units, 0.0, 1.0)
    return (
        straight if lim.linear_mps is None else min(straight, lim.linear_mps),
        turning if lim.angular_radps is None else min(turning, lim.angular_radps),
    )


def fields(
    robot: RobotConfig, units: Mapping[str, UnitConfig], linear_x: float, angular_z: float
) -> dict[str, tuple[float, float]]:
    """Each unit's AY/BX for a twist, in its velocity model [min⁻¹]."""
    out = {}
    for name, (a, b) in motor_speeds(robot, linear_x, angular_z).items():
        motor = units[name].velocity_model is VelocityModel.MOTOR
        out[name] = (a, b) if motor else ab_to_yx(a, b)
    return out


def headroom(
    robot: RobotConfig, units: Mapping[str, UnitConfig], linear_x: float, angular_z: float
) -> float:
    """How many times the twist the robot's axes allow (∞: none binds): every unit's
    ``limits.velocity`` and the wire's range on the fields it reads, and every wheel's
    axis limit that follows from the robot's limits."""
    scale = math.inf
    for name, values in fields(robot, units, linear_x, angular_z).items():
        for value in values:
            if value:
                wire = VELOCITY.maximum if value > 0 else -VELOCITY.minimum
                scale = min(scale, min(units[name].limits.velocity, wire) / abs(value))
    motors = motor_speeds(robot, linear_x, angular_z)
    for wheel in robot.wheels:
        limit, speed = robot.axis_limit(wheel), motors[wheel.unit][wheel.axis]
        if limit is not None and speed:
            scale = min(scale, limit / abs(speed))
    return scale
