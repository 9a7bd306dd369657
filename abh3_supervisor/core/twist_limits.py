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
    return (
        _along(robot, units, (1.0, 0.0), robot.limits.linear_mps),
        _along(robot, units, (0.0, 1.0), robot.limits.angular_radps),
    )


def _along(
    robot: RobotConfig,
    units: Mapping[str, UnitConfig],
    twist: tuple[float, float],
    own: float | None,
) -> float:
    """How many times ``twist`` (a unit twist) the robot may go: the tightest bound."""
    scale = math.inf if own is None else own
    motors = motor_speeds(robot, *twist)
    for name, (a, b) in motors.items():
        cfg = units[name]
        fields = (a, b) if cfg.velocity_model is VelocityModel.MOTOR else ab_to_yx(a, b)
        for value in fields:
            if value:
                wire = VELOCITY.maximum if value > 0 else -VELOCITY.minimum
                scale = min(scale, min(cfg.limits.velocity, wire) / abs(value))
    for wheel in robot.wheels:
        limit, speed = robot.axis_limit(wheel), motors[wheel.unit][wheel.axis]
        if limit is not None and speed:
            scale = min(scale, limit / abs(speed))
    return scale
