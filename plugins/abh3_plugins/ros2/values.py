"""What every incoming value passes before it can reach a drive, and the warning a refusal
gives (once per 5 s per topic, so a flood cannot fill the log)."""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from abh3_supervisor.plugin_api import Scale

log = logging.getLogger("abh3_plugins.ros2.bridge")
WARN_EVERY_S = 5.0


class Refused(ValueError):
    """An incoming value that must not reach a drive."""


def within(scale: Scale | None, *values: float) -> None:
    """Finite, and within ``scale``'s wire range when given."""
    for v in values:
        if not math.isfinite(v):
            raise Refused(f"{v} is not a finite number")
        if scale is not None and not scale.minimum <= v <= scale.maximum:
            raise Refused(
                f"{v:g} is beyond the protocol's range {scale.minimum:g} … {scale.maximum:g}"
            )


def twist(msg: Any, linear_x: float, angular_z: float) -> Any:
    return msg.Twist(linear=msg.Vector3(x=linear_x), angular=msg.Vector3(z=angular_z))


def twist_values(m: Any) -> tuple[float, float]:
    """linear.x and angular.z of a Twist; every component must be finite."""
    values = (m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z)
    within(None, *values)
    return m.linear.x, m.angular.z


class Guard:
    """Wraps a topic's handler: a refused value is dropped with a rate-limited warning
    naming ``who`` (a unit or a robot)."""

    def __init__(self, who: str) -> None:
        self.who = who
        self._warned: dict[str, float] = {}

    def __call__(self, topic: str, handle: Callable[[Any], None]) -> Callable[[Any], None]:
        def guarded(sample: Any) -> None:
            try:
                handle(sample)
            except Refused as exc:
                self.warn(topic, f"ros2: {self.who}: {topic} refused: {exc}")

        return guarded

    def warn(self, topic: str, text: str) -> None:
        now = time.monotonic()
        if now - self._warned.get(topic, -math.inf) >= WARN_EVERY_S:
            self._warned[topic] = now
            log.warning("%s", text)
