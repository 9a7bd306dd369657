"""Where a simulated robot really went: its pose integrated from the simulated motors'
speeds (not from the pulse counts odometry reads), in small fake-clock steps."""

from __future__ import annotations

import math
from collections.abc import Callable

from abh3_supervisor.core.robot import RobotConfig, Side


class Truth:
    """``motor(unit, axis)``: a simulated motor's speed now [min⁻¹]."""

    def __init__(self, robot: RobotConfig, motor: Callable[[str, int], float]) -> None:
        self.robot, self.motor = robot, motor
        self.x = self.y = self.yaw = 0.0

    def twist(self) -> tuple[float, float]:
        left, right = (
            _mean(
                [
                    w.ground_speed(self.motor(w.unit, w.axis))
                    for w in self.robot.wheels
                    if w.side is s
                ]
            )
            for s in (Side.LEFT, Side.RIGHT)
        )
        return (left + right) / 2, (right - left) / self.robot.track_m

    def step(self, dt: float) -> None:
        """Move on by ``dt`` at the motors' speeds now (midpoint heading)."""
        v, w = self.twist()
        heading = self.yaw + w * dt / 2
        self.x += v * math.cos(heading) * dt
        self.y += v * math.sin(heading) * dt
        self.yaw += w * dt


def _mean(values: list[float]) -> float:
    return sum(values) / len(values)
