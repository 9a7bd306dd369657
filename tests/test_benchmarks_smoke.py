"""Smoke mode for the benchmarks: they run and produce sane figures. No timed assertions."""

from __future__ import annotations

import subprocess
import sys

import can
import pytest

from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime import netns
from benchmarks import alone, attached, bus_model, cycle_timing, estop, host_cpu, scale


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
    assert host_cpu.bare(50) > 0 and host_cpu.ours(50) > 0 and host_cpu.event_loop(50) > 0
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


@pytest.mark.wallclock
def test_supervisor_alone_runs() -> None:
    """Section 10: the supervisor, a bare python-can host and the simulator each timed as a
    process of its own on udp_multicast, in a namespace with only lo (skipped where none
    can be made, as the benchmark itself says)."""
    if (why := netns.unavailable()) is not None:
        pytest.skip(f"section 10 needs a network namespace: {why}")
    figures = alone.alone(1.0)
    assert figures["ours_us"] > 0 and figures["bare_us"] > 0 and figures["simulator_us"] > 0
    assert figures["rate_error_percent"] < 50  # every unit's commands were heard on the wire
    baseline = alone.in_process(1.0)
    assert baseline["cpu_percent"] > 0 and baseline["rate_error_percent"] < 50


def test_supervisor_alone_is_skipped_with_the_reason(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(netns, "unavailable", lambda: "not installed: unshare")
    assert alone.rows(1.0, 1) == []
    assert "section 10 skipped: not installed: unshare" in capsys.readouterr().out


def test_supervisor_alone_reads_exchanges_and_timing_off_the_wire() -> None:
    """On made-up frames: replies in the window are the exchanges; the commands give each
    unit's rate and the period's jitter."""
    period = 1 / alone.RATE
    heard = []
    for unit in range(alone.UNITS):
        cmd = ids.dp0_command_id(unit + 1, alone.HOST)
        reply = ids.dp0_reply_id(unit + 1, alone.HOST)
        for k in range(101):
            late = 0.001 if unit == 0 and k % 10 == 5 else 0.0  # 1 in 10 of u0's: 1 ms late
            heard += [(k * period + late, cmd), (k * period + 0.0005, reply)]
    heard.append((0.5, ids.dp0_reply_id(9, alone.HOST)))  # another unit's: not counted
    wire = alone.Wire(sorted(heard))
    window = alone.Window(0.0, 0.999, {})
    assert wire.exchanges(window) == alone.UNITS * 100
    figures = wire.timing(window)
    assert figures["rate_error_percent"] == pytest.approx(0.0, abs=0.01)
    assert figures["jitter_p99_ms"] == pytest.approx(1.0, abs=0.01)  # 20 of 396 periods


@pytest.mark.wallclock
def test_supervisor_alone_gives_up_on_a_process_that_never_says_ready(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A simulator, listener or bare host that never prints its ready line ends the run
    with the reason, instead of hanging the benchmark."""
    monkeypatch.setattr(alone, "START_TIMEOUT_S", 0.2)
    silent = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(60)"], stdout=subprocess.PIPE, text=True
    )
    try:
        with pytest.raises(RuntimeError, match=r"the listener: not ready within 0\.2 s"):
            alone._line(silent, "the listener")
    finally:
        silent.kill()
        silent.communicate()
