"""Dead reckoning from the drive's pulse counts (broadcast 4), with the seed's geometry.

Axis A is the left wheel and B the right one, as the seed's velocity model implies
(``X = A − Y`` and ``angular.z = −X · …``: A faster than B turns clockwise). Counts are
int32 and wrap; a step is taken modulo 2³².
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from abh3_supervisor.core.kinematics import Geometry


@dataclass(frozen=True, slots=True)
class Pose:
    x: float = 0.0  # [m]
    y: float = 0.0  # [m]
    yaw: float = 0.0  # [rad], counter-clockwise, in (−π, π]


def _step(new: int, old: int) -> int:
    """Signed difference of two int32 counters, across a wrap."""
    return (new - old + (1 << 31)) % (1 << 32) - (1 << 31)


class PulseOdometry:
    """Integrates pose from successive (pulse A, pulse B) readings; starts at the origin."""

    def __init__(self, geometry: Geometry) -> None:
        if geometry.pulses_per_rev <= 0:
            raise ValueError("odometry needs geometry.pulses_per_rev")
        self.metres_per_pulse = geometry.metres_per_motor_rev / geometry.pulses_per_rev
        self.width = geometry.width
        self.pose = Pose()
        self._last: tuple[int, int] | None = None

    def update(self, pulse_a: int, pulse_b: int) -> Pose:
        if self._last is not None:
            left = _step(pulse_a, self._last[0]) * self.metres_per_pulse
            right = _step(pulse_b, self._last[1]) * self.metres_per_pulse
            distance, turn = (left + right) / 2, (right - left) / self.width
            p = self.pose
            heading = p.yaw + turn / 2  # midpoint: exact for arcs to second order
            yaw = math.atan2(math.sin(p.yaw + turn), math.cos(p.yaw + turn))
            self.pose = Pose(
                p.x + distance * math.cos(heading), p.y + distance * math.sin(heading), yaw
            )
        self._last = (pulse_a, pulse_b)
        return self.pose


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)
