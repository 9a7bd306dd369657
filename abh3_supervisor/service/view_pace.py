"""The live view's pace: the pushed state slows while the buses' steps come late.

A pushed state costs the loop about 0.1 ms a unit, 10 times a second: an attached TUI
is about an eighth of what the supervisor spends with a recording and the ROS 2 bridge,
most of it the pushes (docs/performance.md, section 12, "The view gives way"). On a small
computer, or under a container's CPU quota, a loop short of CPU brings the buses' steps
late; a view that kept its rate would take from them what they lack. So whenever a bus
step came more than :data:`LATE_S` after its deadline since the last push, the pushes
come half as often (down to :data:`MIN_HZ`); after :data:`CALM_S` without such a step,
twice as often again, one step at a time, up to the rate asked for. The buses, the
recording, the bridge and every plugin keep their pace: only what a person watches gives
way, and it says so (the state's ``slowed``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from abh3_supervisor.runtime.bus_runtime import Runtime

# a step this late is a loop short of CPU (a whole period at 100 Hz), not a moment's
# wait for the GIL or a scheduler's hiccup
LATE_S = 0.010
CALM_S = 10.0  # this long without one: one step back towards the rate asked for
MIN_HZ = 1.0  # the slowest the view gets (a slower rate asked for is kept)
MAX_SLOWDOWN = 16  # 10 Hz asked: 5, 2.5, 1.25, then 1 Hz
# a late step told this long after the last push is old news (the start-up's, before any
# client subscribed): the pushes come at least every 1 / MIN_HZ while anyone watches
STALE_S = 2.0


class ViewPace:
    """Shared by every client of every socket (``late()`` forgets what it says): it says
    the most a bus step came late since it was last asked; ``clock()``, the loop's time."""

    def __init__(self, late: Callable[[], float], clock: Callable[[], float]) -> None:
        self._late, self._clock = late, clock
        self.slowdown = 1  # the pushes come this many times less often than asked
        self.late_s = 0.0  # the lateness that last slowed them
        self._since = -math.inf  # when the slowdown last changed
        self._asked_at = -math.inf  # when the late steps were last asked for

    def period(self, asked: float) -> float:
        """The time until the next push, for a client that asked for one every ``asked``."""
        now, late = self._clock(), self._late()
        fresh, self._asked_at = now - self._asked_at <= STALE_S, now
        if late > LATE_S and fresh:
            self.late_s, self._since = late, now
            self.slowdown = min(2 * self.slowdown, MAX_SLOWDOWN)
        elif self.slowdown > 1 and now - self._since >= CALM_S:
            self._since = now
            self.slowdown //= 2
        return max(asked, min(asked * self.slowdown, 1 / MIN_HZ))

    def to_json(self) -> dict[str, Any] | None:
        """What the state says of it: none at the rate asked for."""
        if self.slowdown == 1:
            return None
        return {"by": self.slowdown, "late_ms": round(self.late_s * 1e3, 1)}


def of_runtime(rt: Runtime) -> ViewPace:
    """The pace of ``rt``'s buses (its pumps' late steps), for every socket it serves."""
    return ViewPace(
        lambda: max((pump.take_late() for pump in rt.pumps.values()), default=0.0),
        rt.supervisor.clock,
    )
