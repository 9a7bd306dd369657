"""Section 10's runs (benchmarks/alone.py): the supervisor's and the bare host's windows
alternate, and the CPU-per-exchange target must hold in every run, not only in the
medians. On made-up figures: no process is started."""

from __future__ import annotations

import os

import pytest

from abh3_supervisor.runtime import netns
from benchmarks import alone


def test_windows_alternate_unless_told_not_to() -> None:
    assert alone.window_order(3, True, True) == [True, False] * 3
    assert alone.window_order(2, True, False) == [True, True, False, False]
    assert alone.window_order(2, False, True) == [True, True]  # no bare host: ours only


def _run(ours_us: float, bare_us: float) -> dict[str, float]:
    return {
        "ours_us": ours_us,
        "bare_us": bare_us,
        "ratio": ours_us / bare_us,
        "simulator_us": 300.0,
        "ours_cpu_percent": 8.0,
        "rate_error_percent": 0.01,
        "jitter_p99_ms": 0.08,
    }


@pytest.mark.parametrize(
    ("runs", "ok"),
    [
        ([_run(115, 100), _run(120, 100), _run(125, 100)], True),
        # the medians say 1.2x, but one run's pair read 1.3x: missed (target 1.25x)
        ([_run(115, 100), _run(120, 100), _run(130, 100)], False),
    ],
)
def test_the_target_holds_in_every_run(
    monkeypatch: pytest.MonkeyPatch, runs: list[dict[str, float]], ok: bool
) -> None:
    monkeypatch.setattr(netns, "unavailable", lambda: None)
    monkeypatch.setattr(alone, "alone_runs", lambda *a, **k: runs)
    monkeypatch.setattr(
        alone,
        "in_process",
        lambda *a, **k: {"cpu_percent": 20.0, "rate_error_percent": 0.01, "jitter_p99_ms": 0.07},
    )
    row = alone.rows(1.0, len(runs), sizing=False)[0]
    assert row.ours == 120 and row.baseline == 100  # the medians, side by side
    assert row.ok is ok
    assert "each run's pair runs 1.15–" in row.target and "ours runs 115–" in row.target


def test_section_2_runs_its_rounds_ours_with_one_setpoint_the_loop_alone_then_bare(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from benchmarks import host_cpu

    calls: list[str] = []

    def ours(exchanges: int, *, new_setpoint: bool = True) -> float:
        calls.append("ours" if new_setpoint else "once")
        return 2.0 if new_setpoint else 1.5

    def bare(exchanges: int) -> float:
        calls.append("bare")
        return 1.0

    def event_loop(exchanges: int) -> float:
        calls.append("loop")
        return 1.2

    monkeypatch.setattr(host_cpu, "ours", ours)
    monkeypatch.setattr(host_cpu, "event_loop", event_loop)
    monkeypatch.setattr(host_cpu, "bare", bare)
    assert host_cpu.interleaved(10, 3) == ([2.0] * 3, [1.5] * 3, [1.2] * 3, [1.0] * 3)
    assert calls == ["ours", "once", "loop", "bare"] * 3


def test_section_2_pinned_runs_every_round_on_one_core_and_gives_the_cores_back(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The pinned rounds run on one core (the threads they start inherit it); afterwards
    the process may use every core it could before."""
    from benchmarks import host_cpu

    before = os.sched_getaffinity(0)
    seen: list[set[int]] = []

    def measured(exchanges: int, **_: object) -> float:
        seen.append(os.sched_getaffinity(0))
        return 1.0

    monkeypatch.setattr(host_cpu, "ours", measured)
    monkeypatch.setattr(host_cpu, "event_loop", measured)
    monkeypatch.setattr(host_cpu, "bare", measured)
    host_cpu.interleaved(10, 2, pinned=True)
    expected = {max(before)} if len(before) > 1 else before
    assert seen == [expected] * 8
    assert os.sched_getaffinity(0) == before
    host_cpu.interleaved(10, 1)
    assert seen[8:] == [before] * 4
