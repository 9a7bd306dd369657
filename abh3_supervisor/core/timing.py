"""Periodic deadlines shared by the scheduler and the simulator."""

from __future__ import annotations


def next_on_grid(due: float, interval: float, now: float) -> float:
    """The next due time on the grid; after a stall, restart from now rather than burst."""
    due += interval
    return due if due > now else now + interval
