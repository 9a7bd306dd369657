"""The seed conversion node's three velocity models (protocol doc §7).

Robot twist (linear.x m/s, angular.z rad/s) ↔ travel/turn Y/X ↔ motor A/B, velocities in
min⁻¹ at the motor. Formulas and defaults are the vendor's, so results match ros2ABH3Cnv.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Geometry:
    """Seed parameters: ``rateNum``/``rateDen`` gear ratio, ``wheel`` diameter, ``width`` track."""

    rate_num: float = 1.0
    rate_den: float = 10.0
    wheel: float = 0.1
    width: float = 0.5
    # encoder pulses per motor revolution (broadcast 4 counts); 0: unknown, no odometry
    pulses_per_rev: float = 0.0

    @property
    def metres_per_motor_rev(self) -> float:
        return self.rate_num / self.rate_den * self.wheel * math.pi


def ab_to_yx(a: float, b: float) -> tuple[float, float]:
    y = (a + b) / 2
    return y, a - y


def yx_to_ab(y: float, x: float) -> tuple[float, float]:
    return y + x, y - x


def yx_to_twist(y: float, x: float, g: Geometry) -> tuple[float, float]:
    """Y/X [min⁻¹] → (linear.x [m/s], angular.z [rad/s])."""
    k = g.metres_per_motor_rev / 60
    return y * k, -x * k / (g.width / 2)


def twist_to_yx(linear_x: float, angular_z: float, g: Geometry) -> tuple[float, float]:
    """(linear.x [m/s], angular.z [rad/s]) → Y/X [min⁻¹]."""
    k = 60 / g.metres_per_motor_rev
    return linear_x * k, -angular_z * k * (g.width / 2)


def twist_to_ab(linear_x: float, angular_z: float, g: Geometry) -> tuple[float, float]:
    return yx_to_ab(*twist_to_yx(linear_x, angular_z, g))


def ab_to_twist(a: float, b: float, g: Geometry) -> tuple[float, float]:
    return yx_to_twist(*ab_to_yx(a, b), g)
