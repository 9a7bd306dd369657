"""The bus loop's budget, counted (issue 50): Python calls per period of four DP0
exchanges, with an .mcap recording and the control socket — a count, so the bound does
not move with the machine's speed (benchmarks/calls.py, section 13)."""

from __future__ import annotations

import pytest

from abh3_supervisor.runtime import netns
from benchmarks import calls


@pytest.mark.skipif(netns.unavailable() is not None, reason=str(netns.unavailable()))
def test_the_loop_makes_at_most_300_python_calls_a_period_with_a_recording() -> None:
    (row,) = calls.counts(1, only=(calls.MCAP_ROW,))
    py, builtins = row[calls.MCAP_ROW]
    assert py <= calls.TARGET, f"{py:.0f} Python calls a period (builtins {builtins:.0f})"
    assert builtins > 0  # the count ran
