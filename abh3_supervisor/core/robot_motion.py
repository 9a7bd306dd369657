"""A robot's twist, decided once for all its drives: its limits, its ramp, one clamp.

A twist to a robot becomes each of its units' (A, B) motor speeds in one decision: the
robot's linear and angular limits, then its acceleration ramp, then the one factor that
keeps every axis within its unit's limits and the robot's own — applied to the whole
twist, so a robot asked to go straight never turns because one side saturated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from abh3_supervisor.config.model import UnitConfig
from abh3_supervisor.core.robot import RobotConfig, ramp, within_robot_limits
from abh3_supervisor.core.twist_limits import fields, headroom


@dataclass(frozen=True, slots=True)
class Plan:
    target: tuple[float, float]  # the twist asked (linear.x, angular.z)
    t: float
    twist: tuple[float, float]  # the twist applied: within limits, ramp and axes
    fields: dict[str, tuple[float, float]]  # per unit, AY/BX in its velocity model
    note: str | None  # what limited the twist, for the operator
    ramping: bool  # the ramp has not reached the (limited) target yet


class RobotMotion:
    """One robot's twist state: the last plan, from which the ramp steps on."""

    def __init__(self, robot: RobotConfig, units: dict[str, UnitConfig]) -> None:
        self.robot = robot
        self.units = {name: units[name] for name in robot.units}
        # the ramp steps at the robot's fastest command period
        self.step_s = min(1.0 / u.command_rate_hz for u in self.units.values())
        self.last: Plan | None = None
        self.step_pending = False  # a ramp step is scheduled

    def reset(self) -> None:
        """The robot was stopped (or commanded otherwise): the next twist ramps from rest."""
        self.last = None

    def plan(self, linear_x: float, angular_z: float, now: float) -> Plan:
        """The robot's plan for a twist now (the same plan for every unit of one turn)."""
        last = self.last
        if last is not None and last.target == (linear_x, angular_z) and last.t == now:
            return last
        robot = self.robot
        scale = within_robot_limits(robot, linear_x, angular_z)
        limited = (linear_x * scale, angular_z * scale)
        # from rest, the first step is one period's worth: it moves at once
        before, since = (last.twist, last.t) if last is not None else ((0.0, 0.0), -math.inf)
        ramped = ramp(robot, before, limited, min(now - since, self.step_s))
        axes = self._axis_scale(*ramped)
        twist = (ramped[0] * axes, ramped[1] * axes)
        notes = []
        if scale < 1.0:
            notes.append(self._robot_limit(linear_x, angular_z, scale))
        if axes < 1.0:
            notes.append("an axis at its speed limit: the whole twist scaled alike")
        note = None
        if notes:
            note = (
                f"robot {robot.name}: twist {linear_x:g} {angular_z:g} → "
                f"{twist[0]:.4g} {twist[1]:.4g} ({'; '.join(notes)})"
            )
        self.last = Plan(
            (linear_x, angular_z),
            now,
            twist,
            fields(self.robot, self.units, *twist),
            note,
            ramped != limited,
        )
        return self.last

    def _robot_limit(self, linear_x: float, angular_z: float, scale: float) -> str:
        lim = self.robot.limits
        if lim.linear_mps is not None and abs(linear_x) * scale >= lim.linear_mps * (1 - 1e-9):
            return f"limits.linear_mps {lim.linear_mps:g}"
        return f"limits.angular_radps {lim.angular_radps:g}"

    def preview(self, linear_x: float, angular_z: float) -> dict[str, tuple[float, float]]:
        """Each unit's fields for a twist as asked, no limit, no ramp, nothing kept: what
        a check before submitting needs (the sign and whether it moves)."""
        return fields(self.robot, self.units, linear_x, angular_z)

    def _axis_scale(self, linear_x: float, angular_z: float) -> float:
        """The one factor (≤ 1) that keeps every axis within its bounds."""
        return min(1.0, headroom(self.robot, self.units, linear_x, angular_z))
