"""The live view's pace: the pushed state slows while the buses' steps come late.

A pushed state costs the loop about 0.1 ms a unit, 10 times a second: an attached TUI
is about an eighth of what the supervisor spends with a recording and the ROS 2 bridge,
most of it the pushes (docs/performance.md, section 12, "The view gives way"). On a small
computer, or under a container's CPU quota, a loop short of CPU brings the buses' steps
late; a view that kept its rate would take from them what they lack. So whenever a bus
step came more than :data:`LATE_S` after its deadline since the last push, or the
process's CPU quota held it back (its cgroup says so: runtime/cgroups.py — steps held
back a few ms fall short of LATE_S yet cost the jitter a small board allows), the pushes
come half as often (down to :data:`MIN_HZ`); after :data:`CALM_S` without either,
twice as often again, one step at a time, up to the rate asked for. The buses, the
recording, the bridge and every plugin keep their pace: only what a person watches gives
way, and it says so (the state's ``slowed``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from abh3_supervisor.runtime import cgroups

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
    """Shared by every client of every socket (``late()`` and ``held()`` forget what they
    say): the most a bus step came late since last asked, and whether the CPU quota held
    the process back since; ``clock()``, the loop's time."""

    def __init__(
        self,
        late: Callable[[], float],
        clock: Callable[[], float],
        held: Callable[[], bool] = lambda: False,
    ) -> None:
        self.late, self.clock, self.held = late, clock, held
        self.slowdown = 1  # the pushes come this many times less often than asked
        self.late_s = 0.0  # the lateness when they were last slowed
        self.quota = False  # whether the CPU quota was what last slowed them
        self._since = -math.inf  # when the slowdown last changed
        self._asked_at = -math.inf  # when the late steps were last asked for

    def period(self, asked: float) -> float:
        """The time until the next push, for a client that asked for one every ``asked``."""
        now, late, held = self.clock(), self.late(), self.held()
        fresh, self._asked_at = now - self._asked_at <= STALE_S, now
        if (late > LATE_S or held) and fresh:
            self.late_s, self.quota, self._since = late, late <= LATE_S, now
            self.slowdown = min(2 * self.slowdown, MAX_SLOWDOWN)
        elif self.slowdown > 1 and now - self._since >= CALM_S:
            self._since = now
            self.slowdown //= 2
        return max(asked, min(asked * self.slowdown, 1 / MIN_HZ))

    def to_json(self) -> dict[str, Any] | None:
        """What the state says of it: none at the rate asked for."""
        if self.slowdown == 1:
            return None
        return {"by": self.slowdown, "late_ms": round(self.late_s * 1e3, 1), "quota": self.quota}


def of_runtime(rt: Runtime) -> ViewPace:
    """The pace of ``rt``'s buses (its pumps' late steps, this process's CPU quota), for
    every socket it serves."""
    return ViewPace(
        lambda: max((pump.take_late() for pump in rt.pumps.values()), default=0.0),
        rt.supervisor.clock,
        cgroups.Throttling(cgroups.cpu_dir()).held,
    )
