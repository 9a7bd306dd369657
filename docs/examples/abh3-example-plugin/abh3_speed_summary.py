"""``speed_summary``: the peak speed of every unit, written as JSON when the run ends.

YAML::

    plugins:
      speed_summary:
        path: speeds.json      # where the summary goes
        warn_above: 3000       # min⁻¹; a notice is logged the first time a unit exceeds it
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from abh3_supervisor.plugin_api import Feedback, Section, SupervisorView, hookimpl

log = logging.getLogger(__name__)


class SpeedSummary:
    def __init__(self) -> None:
        self.path = Path("speeds.json")
        self.warn_above = 3000.0
        self.peak: dict[str, float] = {}
        self.samples: dict[str, int] = {}

    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        section.only({"path", "warn_above"})
        self.path = Path(section.text("path", str(self.path)))
        self.warn_above = section.number("warn_above", self.warn_above, 0.0, 6553.4)

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback) -> None:  # fewer args than the spec
        speed = max(abs(feedback.vel_a), abs(feedback.vel_b))
        if speed > self.warn_above >= self.peak.get(unit, 0.0):
            log.warning("unit %s above %g min⁻¹", unit, self.warn_above)
        self.peak[unit] = max(self.peak.get(unit, 0.0), speed)
        self.samples[unit] = self.samples.get(unit, 0) + 1

    @hookimpl
    def abh3_stop(self, supervisor: SupervisorView) -> None:
        summary = {
            u: {"peak_min-1": self.peak.get(u, 0.0), "samples": self.samples.get(u, 0)}
            for u in supervisor.units
        }
        self.path.write_text(json.dumps(summary, indent=2), encoding="utf-8")
