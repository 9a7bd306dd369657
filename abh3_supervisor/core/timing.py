"""Periodic deadlines shared by the scheduler and the simulator."""

from __future__ import annotations

import math


def next_on_grid(due: float, interval: float, now: float) -> float:
    """The next due time on the grid; after a stall, the first grid point after now (the
    missed ones are skipped rather than sent in a burst). The grid keeps its phase, so
    turns staggered over a period stay staggered, and a turn's units together, after a
    stall: the loop keeps waking for whole turns, not for each unit."""
    due += interval
    if due > now:
        return due
    due += (math.floor((now - due) / interval) + 1) * interval
    return due if due > now else due + interval  # now on a point, within rounding
