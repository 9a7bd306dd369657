"""Smoke mode for the benchmarks: they run and produce sane figures. No timed assertions."""

from __future__ import annotations

import can
import pytest

from abh3_supervisor.protocol import frames, ids
from benchmarks import attached, bus_model, cycle_timing, estop, host_cpu, scale


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


def test_estop_row_runs_at_both_rates() -> None:
    """The e-stop row: requests over the socket from another process, stop frames read back
    from a second virtual bus on the channel; every e-stop found the unit armed."""
    for rate in (10, 100):
        figures = estop.measure(rate, 3)
        assert figures["samples"] == 3 and figures["unarmed"] == 0
        assert 0 < figures["p50_ms"] <= figures["p99_ms"] <= figures["max_ms"]


def test_estop_row_times_the_first_stop_frame_after_the_request() -> None:
    """The matching, on made-up frames: a START-on frame after the request is not the stop,
    and a request while the unit was not armed is counted, not timed."""
    start = 0x4
    cmd = ids.dp0_command_id(estop.ABH3, estop.HOST)

    def frame(t: float, ay: int, inputs: int) -> can.Message:
        data = frames.encode_dp0_command(ay, 0, inputs)
        return can.Message(timestamp=t, arbitration_id=cmd, data=data, is_extended_id=True)

    wire = [
        frame(1.0, 300, start | 1),
        frame(2.001, 300, start | 1),  # scheduled, already on its way: not the stop
        frame(2.003, 0, 1),  # the stop frame: 3 ms after the request
        frame(2.5, 0, 1),
        frame(3.010, 0, 1),
        can.Message(timestamp=2.002, arbitration_id=cmd + 1, data=bytes(8), is_extended_id=True),
    ]
    found, unarmed = estop.latencies(wire, [2.0, 3.0], start)
    assert found == [pytest.approx(0.003)] and unarmed == 1
