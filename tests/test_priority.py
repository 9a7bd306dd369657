"""The bus loop's scheduling: real-time where allowed, said either way, restored after."""

from __future__ import annotations

import os
import re
import resource
import sys
import threading
from pathlib import Path

import pytest

from abh3_supervisor.runtime import cgroups, priority
from abh3_supervisor.runtime.priority import Priority, PriorityError, bus_priority


def test_normal_leaves_the_scheduling_alone() -> None:
    before, switch = os.sched_getscheduler(0), sys.getswitchinterval()
    with bus_priority(Priority.NORMAL) as note:
        assert os.sched_getscheduler(0) == before
        assert sys.getswitchinterval() == switch
    assert note == "bus loop at normal priority"


@pytest.mark.skipif(not priority._may_realtime(), reason="needs root or RLIMIT_RTPRIO")
def test_auto_runs_the_loop_and_its_threads_real_time_then_restores() -> None:
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    switch = sys.getswitchinterval()
    seen: list[int] = []
    with bus_priority(Priority.AUTO) as note:
        # another thread running Python holds the loop up for at most this, not 5 ms
        assert sys.getswitchinterval() == pytest.approx(priority.GIL_SWITCH_S)
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
    assert sys.getswitchinterval() == switch


def test_without_permission_auto_says_how_to_allow_it_and_realtime_refuses(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(priority, "_may_realtime", lambda: False)
    before = os.sched_getscheduler(0)
    with bus_priority(Priority.AUTO) as note:
        assert os.sched_getscheduler(0) == before
    assert note.startswith("bus loop at normal priority: real-time scheduling refused")
    assert f"LimitRTPRIO={priority.FIFO_PRIORITY}" in note and "rtprio 20" in note
    refused = pytest.raises(PriorityError, match="--priority realtime: real-time scheduling")
    with refused, bus_priority(Priority.REALTIME):
        pytest.fail("must not run without real-time priority")  # pragma: no cover


@pytest.mark.parametrize(
    ("euid", "limit", "allowed"),
    [
        (0, 0, True),  # root
        (1000, priority.FIFO_PRIORITY, True),  # LimitRTPRIO=20, limits.conf's rtprio 20
        (1000, resource.RLIM_INFINITY, True),
        (1000, priority.FIFO_PRIORITY - 1, False),
        (1000, 0, False),  # CAP_SYS_NICE alone (or CPUSchedulingPolicy=) does not count
    ],
)
def test_real_time_is_tried_with_root_or_a_real_time_limit_and_nothing_else(
    monkeypatch: pytest.MonkeyPatch, euid: int, limit: int, allowed: bool
) -> None:
    """What the docs and the log line say is needed is what the check accepts."""
    monkeypatch.setattr(os, "geteuid", lambda: euid)
    monkeypatch.setattr(resource, "getrlimit", lambda which: (limit, resource.RLIM_INFINITY))
    assert priority._may_realtime() is allowed


def test_the_shipped_systemd_unit_allows_what_the_advice_names() -> None:
    root = Path(__file__).resolve().parent.parent
    unit = (root / "docs/examples/systemd/abh3-supervisor.service").read_text()
    (limit,) = re.findall(r"^LimitRTPRIO=(\d+)$", unit, re.MULTILINE)
    assert int(limit) == priority.FIFO_PRIORITY
    assert "CPUSchedulingPolicy" not in unit  # the supervisor sets its own policy
    assert f"LimitRTPRIO={limit}" in priority.HOW_TO_ALLOW
    service = (root / "docs/service.md").read_text()
    assert f"`LimitRTPRIO={limit}`" in service and "CPUSchedulingPolicy=fifo" not in service


def cgroup_v1(tmp_path: Path, rt_runtime_us: int) -> tuple[Path, Path]:
    """A v1 ``cpu`` hierarchy with this process in ``/limited``: the mounts and own files."""
    group = tmp_path / "cpu" / "limited"
    group.mkdir(parents=True)
    (group / "cpu.rt_runtime_us").write_text(f"{rt_runtime_us}\n")
    mounts = tmp_path / "mounts"
    mounts.write_text(
        "proc /proc proc rw 0 0\n"
        f"cgroup {tmp_path / 'cpu'} cgroup rw,relatime,cpu 0 0\n"
        f"cgroup {tmp_path / 'memory'} cgroup rw,relatime,memory 0 0\n"
    )
    own = tmp_path / "cgroup"
    own.write_text("4:memory:/elsewhere\n1:cpu:/limited\n0::/\n")
    return mounts, own


@pytest.mark.parametrize("rt_runtime_us", [0, 950000])
def test_a_user_who_may_is_told_when_the_cgroup_is_what_refuses(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, rt_runtime_us: int
) -> None:
    """Root in a CPU-limited cgroup (a container, a benchmark's limit) is refused by the
    kernel: the advice names the cgroup, not the permissions root already has."""
    mounts, own = cgroup_v1(tmp_path, rt_runtime_us)
    monkeypatch.setattr(cgroups, "MOUNTS", mounts)
    monkeypatch.setattr(cgroups, "OWN", own)
    monkeypatch.setattr(priority, "_may_realtime", lambda: True)

    def refused(pid: int, policy: int, param: object) -> None:
        if policy == os.SCHED_FIFO:
            raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refused)
    with bus_priority(Priority.AUTO) as note:
        pass
    if rt_runtime_us == 0:
        where = tmp_path / "cpu" / "limited" / "cpu.rt_runtime_us"
        assert f"gives real-time tasks no time ({where} is 0" in note
        assert "--priority normal" in note and "LimitRTPRIO" not in note
    else:  # the cgroup is not why: the usual advice
        assert "LimitRTPRIO" in note
