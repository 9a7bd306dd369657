"""Smoke mode for the benchmarks: they run and produce sane figures. No timed assertions."""

from __future__ import annotations

import pytest

from benchmarks import attached, bus_model, cycle_timing, host_cpu, scale


def test_bus_model_reaches_the_physical_limit_deterministically() -> None:
    got, bits = bus_model.ours(8, 500_000, 0.0005)
    limit = bus_model.physical_limit(8, 500_000, 0.0005, bits)
    assert got == pytest.approx(limit, rel=0.02)
    assert 0 < bus_model.seed_style(8, 500_000, 0.0005, 0.0) <= limit * 1.01


def test_planner_matches_the_wire_model() -> None:
    planned, measured = bus_model.planner_accuracy()
    assert planned == pytest.approx(measured, rel=0.05)


@pytest.mark.wallclock
def test_host_cpu_and_timing_and_scale_run() -> None:
    assert host_cpu.bare(50) > 0 and host_cpu.ours(50) > 0
    for tuis in (0, 1):
        result = cycle_timing.run(2, 100, 0.5, f"smoke-{tuis}", tuis=tuis)
        assert set(result) >= {"jitter_p99_ms", "latency_p99_ms", "rate_error_percent"}
    measured = scale.in_subprocess("--units", "2", "--seconds", "1")
    assert measured["units"] == 2 and measured["rss_mb"] > 0


@pytest.mark.wallclock
def test_ros2_bridge_figures_run(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("cyclonedds")
    from abh3_plugins.ros2.dds import LOOPBACK_URI
    from benchmarks import ros2_bridge

    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK_URI)  # restored afterwards
    result = ros2_bridge.vel_cmd_latency(50, 1.0)
    assert result["delivered_percent"] > 50 and result["latency_p99_ms"] > 0
    assert ros2_bridge.cpu_percent(1, 50, 0.5, bridge=True) > 0


@pytest.mark.wallclock
def test_everything_on_jitter_and_memory_run() -> None:
    """The real-process rows: a headless run, TUIs attached, figures from its recording."""
    pytest.importorskip("cyclonedds")
    pytest.importorskip("mcap")
    how, figures = attached.run(1.0, tuis=1)
    assert how in ("tmux", "headless Textual")
    for window in ("alone", "attached"):
        assert figures[f"{window}_jitter_p99_ms"] > 0
        assert figures[f"{window}_rate_error_percent"] < 50  # frames were read back
    memory = attached.memory(2.0, warmup=2.0)
    assert memory["rss_start_mb"] > 10 and memory["rss_end_mb"] > 10
