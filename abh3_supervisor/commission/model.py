"""What a commissioning run measures and decides: checks, traces, settings and their bounds."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from abh3_supervisor.errors import Abh3Error

AXES = ("A", "B")  # the motors; every jog and step moves one of them
MIN_JOG = 2.0  # min⁻¹: ten steps of the wire's 0.2, so that ±15 % of a jog can be told


class Verdict(StrEnum):
    PASS = "pass"
    WARN = "warn"
    FAIL = "fail"
    SKIPPED = "not run"


def overall(checks: list[Check]) -> Verdict:
    """A unit's or a robot's verdict: any fail (or nothing checked) fails; any warning
    or skipped check warns; else it passes."""
    verdicts = {c.verdict for c in checks}
    if Verdict.FAIL in verdicts or not checks:
        return Verdict.FAIL
    if verdicts & {Verdict.WARN, Verdict.SKIPPED}:
        return Verdict.WARN
    return Verdict.PASS


@dataclass(frozen=True, slots=True)
class Check:
    """One line of the summary: what was checked, what was measured against what limit,
    and what to change (a YAML key or a drive parameter address) when it is not a pass."""

    step: str  # identity, e-stop, jog A, step B, …
    name: str
    verdict: Verdict
    measured: str
    limit: str = ""
    fix: str = ""

    def to_json(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "name": self.name,
            "verdict": self.verdict.value,
            "measured": self.measured,
            "limit": self.limit,
            "fix": self.fix,
        }


@dataclass(slots=True)
class Trace:
    """A jog or a step as it happened, for the plots and the JSON: the commands on the wire
    (A/B min⁻¹), the DP0 feedback (every exchange), the currents (broadcast 3, %) and the
    pulse counts (broadcast 4). Times are seconds since the trace began."""

    title: str
    kind: str  # "jog" or "step"
    axis: int
    t0: float  # the bench clock at the trace's start
    command: list[tuple[float, float, float]] = field(default_factory=list)
    feedback: list[tuple[float, float, float]] = field(default_factory=list)
    current: list[tuple[float, float, float]] = field(default_factory=list)
    pulses: list[tuple[float, int, int]] = field(default_factory=list)
    stopped: str | None = None  # the guard stopped the unit: why

    def to_json(self) -> dict[str, Any]:
        def cols(rows: list[Any], names: tuple[str, ...]) -> dict[str, list[Any]]:
            return {n: [r[i] for r in rows] for i, n in enumerate(names)}

        return {
            "title": self.title,
            "kind": self.kind,
            "axis": AXES[self.axis],
            "stopped": self.stopped,
            "command": cols(self.command, ("t", "a", "b")),
            "feedback": cols(self.feedback, ("t", "a", "b")),
            "current": cols(self.current, ("t", "a", "b")),
            "pulses": cols(self.pulses, ("t", "a", "b")),
        }


class SettingsError(Abh3Error):
    """A commissioning option outside its bounds: the user's mistake (exit 2)."""


@dataclass(frozen=True, slots=True)
class Settings:
    """How hard commissioning may push. Speeds are fractions of the unit's
    ``limits.velocity``; every command of the run stays within ``jog_fraction`` of it."""

    jog_fraction: float = 0.05
    jog_s: float = 0.8  # per direction
    step_s: float = 0.8
    scale_tolerance: float = 0.05  # measured pulses per revolution against the YAML's
    # the step response's limits (the report states them)
    rise_max_s: float = 0.3
    overshoot_max: float = 0.15
    settling_max_s: float = 0.6
    steady_error_max: float = 0.03
    current_max: float = 150.0  # %

    BOUNDS = {  # noqa: RUF012 (a class constant, read by check())
        "jog_fraction": (0.01, 0.2, "of limits.velocity"),
        "jog_s": (0.2, 1.0, "s"),
        "step_s": (0.3, 1.0, "s"),
        "scale_tolerance": (0.005, 0.5, ""),
    }

    @staticmethod
    def flag(key: str) -> str:
        """The command-line option that sets ``key``."""
        return {"jog_s": "--jog-seconds", "step_s": "--step-seconds"}.get(
            key, "--" + key.replace("_", "-")
        )

    def check(self) -> Settings:
        for key, (lo, hi, unit) in self.BOUNDS.items():
            value = getattr(self, key)
            if not lo <= value <= hi:
                raise SettingsError(
                    f"{self.flag(key)} {value:g} is out of bounds "
                    f"(allowed {lo:g}–{hi:g} {unit})".rstrip()
                )
        return self

    def jog_speed(self, velocity_limit: float) -> float:
        """Rounded down to 0.4 min⁻¹: half of it (one motor as travel and turn) is still on
        the wire's 0.2 min⁻¹ grid, so no frame carries more than this."""
        return round(math.floor(self.jog_fraction * velocity_limit / 0.4 + 1e-9) * 0.4, 1)

    def too_slow(self, unit: str, velocity_limit: float) -> str | None:
        """Why ``unit``'s jog would be too slow to judge (a speed of 0 would pass every jog
        by moving nothing), or None."""
        speed = self.jog_speed(velocity_limit)
        if speed >= MIN_JOG:
            return None
        return (
            f"units.{unit}.limits.velocity {velocity_limit:g} × --jog-fraction "
            f"{self.jog_fraction:g} is a jog of {speed:g} min⁻¹, below the {MIN_JOG:g} min⁻¹ "
            "a jog needs to be judged: raise --jog-fraction (up to 0.2) or the limit"
        )

    def to_json(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in self.__slots__}
