"""``/diagnostics``: every bus and unit as ``diagnostic_msgs/DiagnosticArray``.

Published at ``diagnostics_hz`` (1 Hz, what ROS drivers' diagnostic updaters use) and at
once when any level changes, so a drive's error reaches ``rqt_robot_monitor`` as soon as
the supervisor has read it, not up to a period later. What each level means is in
:mod:`abh3_supervisor.core.diagnostics`. Sans-I/O: the caller passes the time in.

Each report is a fresh snapshot from the plugin's view (:class:`ViewHealth`:
``SupervisorView.health()``, frozen, read safely from this plugin's threads while the bus
loop runs); the publisher keeps no live object of the supervisor.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from abh3_plugins.ros2.transport import Publish
from abh3_supervisor.plugin_api import Level, Status, SupervisorView

log = logging.getLogger(__name__)
TOPIC = "/diagnostics"  # global, as every ROS driver publishes it


def diagnostic_array(msg: Any, statuses: Sequence[Status], stamp_ns: int) -> Any:
    return msg.DiagnosticArray(
        header=msg.Header(
            stamp=msg.Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        ),
        status=[
            msg.DiagnosticStatus(
                level=msg.byte(int(s.level)),
                name=s.name,
                message=s.message,
                hardware_id=s.hardware_id,
                values=[msg.KeyValue(key=k, value=v) for k, v in s.values],
            )
            for s in statuses
        ],
    )


class Statuses(Protocol):
    """Where the statuses come from: :class:`ViewHealth` in a run; a test may give the
    supervisor's own ``Health`` on its single thread."""

    def statuses(self, now: float) -> Sequence[Status]: ...


class ViewHealth:
    """Every report a new snapshot from the view (``SupervisorView.health()``), never the
    one before: the snapshot is a copy taken when asked, ``now`` only schedules."""

    def __init__(self, view: SupervisorView) -> None:
        self.view = view

    def statuses(self, now: float) -> Sequence[Status]:
        return self.view.health().report


class DiagnosticsPublisher:
    def __init__(
        self,
        health: Statuses,
        publish: Publish,
        msg: Any,
        hz: float,
        wall_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.health, self.publish, self.msg = health, publish, msg
        self.period = 1.0 / hz if hz > 0 else math.inf
        self.wall_ns = wall_ns
        self.next_at = -math.inf
        self.levels: dict[str, Level] = {}
        self.published = 0
        self._lock = threading.Lock()  # ticks on its thread, changes on the plugin's worker

    def tick(self, now: float) -> None:
        """Publish if a period has passed since the last time."""
        with self._lock:
            if now >= self.next_at:
                self._publish(self.health.statuses(now), now)

    def changed(self, now: float) -> None:
        """A unit's health or flags changed: publish now if any level did."""
        with self._lock:
            statuses = self.health.statuses(now)
            if {s.name: s.level for s in statuses} != self.levels:
                self._publish(statuses, now)

    def _publish(self, statuses: Sequence[Status], now: float) -> None:
        self.levels = {s.name: s.level for s in statuses}
        self.next_at = now + self.period
        self.publish(diagnostic_array(self.msg, statuses, self.wall_ns()))
        self.published += 1


class DiagnosticsThread:
    """Runs :meth:`DiagnosticsPublisher.tick` on real time until closed."""

    def __init__(self, publisher: DiagnosticsPublisher) -> None:
        self.publisher = publisher
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ros2-diagnostics", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while True:
            now = time.monotonic()
            try:
                self.publisher.tick(now)
            except Exception:  # one bad report must not end the reports
                log.exception("ros2: publishing /diagnostics failed")
                self.publisher.next_at = now + self.publisher.period
            if self._stop.wait(max(0.0, self.publisher.next_at - now)):
                return

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
