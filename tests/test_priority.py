"""The bus loop's scheduling: real-time where allowed, said either way, restored after."""

from __future__ import annotations

import os
import threading

import pytest

from abh3_supervisor.runtime import priority
from abh3_supervisor.runtime.priority import Priority, PriorityError, bus_priority


def test_normal_leaves_the_scheduling_alone() -> None:
    before = os.sched_getscheduler(0)
    with bus_priority(Priority.NORMAL) as note:
        assert os.sched_getscheduler(0) == before
    assert note == "bus loop at normal priority"


@pytest.mark.skipif(not priority._may_realtime(), reason="needs root or RLIMIT_RTPRIO")
def test_auto_runs_the_loop_and_its_threads_real_time_then_restores() -> None:
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    seen: list[int] = []
    with bus_priority(Priority.AUTO) as note:
        assert os.sched_getscheduler(0) == os.SCHED_FIFO
        assert os.sched_getparam(0).sched_priority == priority.FIFO_PRIORITY
        # a thread started meanwhile (a bus reader, a plugin's worker) shares the priority:
        # a lower one holding the GIL could hold the loop up behind any other program
        worker = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
        worker.start()
        worker.join()
    assert seen == [os.SCHED_FIFO]
    assert "real-time priority (SCHED_FIFO 20)" in note
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == before


def test_without_permission_auto_says_how_to_allow_it_and_realtime_refuses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(priority, "_may_realtime", lambda: False)
    before = os.sched_getscheduler(0)
    with bus_priority(Priority.AUTO) as note:
        assert os.sched_getscheduler(0) == before
    assert note.startswith("bus loop at normal priority: real-time scheduling refused")
    assert "CPUSchedulingPolicy=fifo" in note and "rtprio" in note
    refused = pytest.raises(PriorityError, match="--priority realtime: real-time scheduling")
    with refused, bus_priority(Priority.REALTIME):
        pytest.fail("must not run without real-time priority")  # pragma: no cover
