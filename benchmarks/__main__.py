"""``python -m benchmarks``: every figure next to its baseline, as ratios, in one run.

``--quick`` is the smoke mode CI runs (short windows, one repetition); ``--long`` adds the
10-minute memory-growth run; ``--small`` runs only section 12, a small computer's budget
(the figures to take on a board). Results are medians of ``--runs`` repetitions.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import statistics

from abh3_supervisor.runtime import netns
from benchmarks import (
    alone,
    attached,
    bursts,
    bus_model,
    calls,
    cycle_timing,
    estop,
    host_cpu,
    recording,
    robot,
    ros2_bridge,
    scale,
    small,
)
from benchmarks.report import Row, machine, print_rows

COUNTS = [1, 4, 8, 16, 32]
BITRATES = [250_000, 500_000, 1_000_000]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    p.add_argument("--quick", action="store_true", help="smoke mode: short and single runs")
    p.add_argument("--long", action="store_true", help="add the 10-minute memory-growth run")
    p.add_argument("--runs", type=int, default=3, help="repetitions; the median is printed")
    p.add_argument(
        "--latency-ms",
        type=float,
        default=0.5,
        help="simulated drive response latency for the bus model (default 0.5)",
    )
    p.add_argument(
        "--small",
        action="store_true",
        help="only section 12: the supervisor in a CPU cgroup at 5/10/25 %% of a core (root)",
    )
    a = p.parse_args(argv)
    runs = 1 if a.quick else a.runs
    if a.small:
        print(f"machine: {machine()}")
        print_rows(small.rows(2.0 if a.quick else 10.0, runs, sizing=not a.quick))
        return 0
    rows: list[Row] = []
    print(f"machine: {machine()}")
    print(
        f"mode: {'quick' if a.quick else 'full'}, median of {runs} run(s); "
        f"bus model drive latency {a.latency_ms} ms"
    )

    # 1. bus utilisation (deterministic model: one run is exact)
    latency = a.latency_ms / 1000
    section = "1. bus utilisation (simulated wire, offered load above capacity)"
    for r in bus_model.utilisation_table(
        COUNTS if not a.quick else [1, 8],
        BITRATES if not a.quick else [500_000],
        latency,
        seed_turnaround=0.0,
    ):
        n, kbit = int(r["units"]), int(r["bitrate"]) // 1000
        rows.append(
            Row(
                section,
                f"{n:>2} units @ {kbit:>4} kbit/s: exchanges/s vs seed-style",
                r["ours"],
                r["seed"],
                "/s",
                "",  # the wire bounds both strategies (docs/performance.md)
            )
        )
        ok = r["percent"] >= 95
        rows.append(
            Row(
                section,
                f"{n:>2} units @ {kbit:>4} kbit/s: % of physical limit",
                r["percent"],
                100.0,
                "%",
                ">=95%",
                ok,
            )
        )
    # what one scheduler per bus buys: status polling offered above the bus's capacity
    # next to 100 Hz commands, the seed-style strategy on the same wire model
    overload = bus_model.polling_overload(8, 500_000, latency)
    (rate_ours, age_ours), (rate_seed, age_seed) = overload["ours"], overload["seed"]
    rows.append(
        Row(
            section,
            " 8 units @100 Hz + polls above capacity: worst command rate",
            100 * rate_ours,
            100 * rate_seed,
            "%",
            ">=99% of requested",
            rate_ours >= 0.99,
        )
    )
    rows.append(
        Row(
            section,
            " 8 units @100 Hz + polls above capacity: command age p99",
            age_ours * 1000,
            age_seed * 1000,
            "ms",
            "<=10 ms (one period)",
            age_ours <= 0.0105,  # one period, within the wire's own frame time
        )
    )

    # 2. host CPU per exchange
    section = "2. host CPU per DP0 exchange (virtual bus, same echo drive)"
    n = 2000 if a.quick else 10000
    for pinned in (False, True):
        ours_runs, once_runs, loop_runs, bare_runs = host_cpu.interleaved(n, runs, pinned=pinned)
        bare = statistics.median(bare_runs) * 1e6
        first = "  both on one core: ours" if pinned else "CPU per exchange: ours"
        where = "on one core, " if pinned else ""
        once = f"  {where or 'the same, '}the setpoint set once"
        for label, runs_of, targeted in (
            (f"{first} vs bare python-can", ours_runs, not pinned),
            (f"{once} (not per exchange)", once_runs, False),
            (f"  {where}an event loop alone (no scheduler, no supervisor)", loop_runs, False),
        ):
            ratios = [o / b for o, b in zip(runs_of, bare_runs, strict=True)]
            notes = ["<=1.5x every run"] if targeted else []
            if runs > 1:
                notes.append(f"each run's pair {min(ratios):.3g}–{max(ratios):.3g}x")
            verdict = max(ratios) <= 1.5 if targeted else None
            median = statistics.median(runs_of) * 1e6
            rows.append(Row(section, label, median, bare, "us", "; ".join(notes), verdict))

    # 3. cycle timing, 8 units at 100 Hz
    section = "3. cycle timing at 100 Hz (baseline: 1 unit headless; TUI rows: 8 units headless)"
    seconds = 2.0 if a.quick else 10.0
    eight = [cycle_timing.run(8, 100, seconds, f"timing8-{i}") for i in range(runs)]
    one = [cycle_timing.run(1, 100, seconds, f"timing1-{i}") for i in range(runs)]

    def med(results: list[dict[str, float]], key: str) -> float:
        return statistics.median(r[key] for r in results)

    rows.append(
        Row(
            section,
            "worst unit's rate error vs requested",
            med(eight, "rate_error_percent"),
            med(one, "rate_error_percent"),
            "%",
            "<=1%",
            med(eight, "rate_error_percent") <= 1,
        )
    )
    rows.append(
        Row(
            section,
            "period jitter p50",
            med(eight, "jitter_p50_ms"),
            med(one, "jitter_p50_ms"),
            "ms",
        )
    )
    rows.append(
        Row(
            section,
            "period jitter p99",
            med(eight, "jitter_p99_ms"),
            med(one, "jitter_p99_ms"),
            "ms",
            "<=1 ms",
            med(eight, "jitter_p99_ms") <= 1,
        )
    )
    rows.append(
        Row(
            section,
            "input-to-frame latency p99",
            med(eight, "latency_p99_ms"),
            med(one, "latency_p99_ms"),
            "ms",
            "<=11 ms (cycle + 1)",
            med(eight, "latency_p99_ms") <= 11,
        )
    )
    # the TUI attached from another process (as `abh3 run` on a terminal and `abh3 tui`)
    tui1 = [cycle_timing.run(8, 100, seconds, f"tui1-{i}", tuis=1) for i in range(runs)]
    tui2 = [cycle_timing.run(8, 100, seconds, f"tui2-{i}", tuis=2) for i in range(runs)]
    headless_jitter = med(eight, "jitter_p99_ms")
    for label, results in (("1 TUI", tui1), ("2 TUIs", tui2)):
        rate, jitter = med(results, "rate_error_percent"), med(results, "jitter_p99_ms")
        latency = med(results, "latency_p99_ms")
        rows.append(
            Row(
                section,
                f"8 units, {label} attached: rate error",
                rate,
                med(eight, "rate_error_percent"),
                "%",
                "<=1%",
                rate <= 1,
            )
        )
        rows.append(
            Row(
                section,
                f"8 units, {label} attached: period jitter p99",
                jitter,
                headless_jitter,
                "ms",
                "<=2 ms, <=1.5x headless",
                jitter <= 2 and jitter <= 1.5 * max(headless_jitter, 0.1),
            )
        )
        rows.append(
            Row(
                section,
                f"8 units, {label} attached: input-to-frame p99",
                latency,
                med(eight, "latency_p99_ms"),
                "ms",
                "<=11 ms",
                latency <= 11,
            )
        )

    # everything on, as operators run it: `abh3 run --headless` with the ROS 2 bridge and an
    # MCAP recording, then two `abh3 tui --connect` in tmux (one on the plots tab); jitter
    # from the run's own recording, before and while they are attached (benchmarks/attached)
    ran = [attached.run(5.0 if a.quick else 20.0) for _ in range(runs)]
    how, on = ran[0][0], [figures for _, figures in ran]
    alone_p99, on_p99 = med(on, "alone_jitter_p99_ms"), med(on, "attached_jitter_p99_ms")
    rows.append(
        Row(
            section,
            f"everything on, 2 TUIs ({how}): period jitter p99",
            on_p99,
            alone_p99,
            "ms",
            "<=2 ms, <=1.5x alone",
            on_p99 <= 2 and on_p99 <= 1.5 * max(alone_p99, 0.1),
        )
    )
    rate = max(med(on, "alone_rate_error_percent"), med(on, "attached_rate_error_percent"))
    rows.append(
        Row(section, "everything on, 2 TUIs: rate error", rate, None, "%", "<=1%", rate <= 1)
    )

    # 4. scale and memory (fresh subprocess per measurement)
    section = "4. scale and memory (simulated drives in the same process)"
    secs = "3" if a.quick else "10"
    one_unit = scale.in_subprocess("--units", "1", "--seconds", secs)
    for count in [1, 4, 8, 16, 32] if not a.quick else [16]:
        m = scale.in_subprocess("--units", str(count), "--seconds", secs)
        rows.append(
            Row(
                section,
                f"{count:>2} units, 1 bus: CPU % of one core (vs 1 unit)",
                m["cpu_percent"],
                one_unit["cpu_percent"],
                "%",
            )
        )
        rows.append(
            Row(
                section,
                f"{count:>2} units, 1 bus: slowest unit's achieved/requested",
                100 * m["min_rate_ratio"],
                100.0,
                "%",
                ">=99%",
                m["min_rate_ratio"] >= 0.99,
            )
        )
        if count == 16:
            base = scale.in_subprocess("--baseline")["rss_mb"]
            rows.append(
                Row(
                    section,
                    "16 units: RSS vs python with python-can only",
                    m["rss_mb"],
                    base,
                    "MB",
                    "<=80 MB",
                    m["rss_mb"] <= 80,
                )
            )
    multi = scale.in_subprocess("--units", "8", "--buses", "4", "--seconds", secs)
    rows.append(
        Row(
            section,
            "4 buses x 8 units: slowest achieved/requested",
            100 * multi["min_rate_ratio"],
            100.0,
            "%",
            ">=99%",
            multi["min_rate_ratio"] >= 0.99,
        )
    )
    growth_secs = "600" if a.long else ("20" if a.quick else "60")
    g = scale.in_subprocess("--units", "16", "--seconds", growth_secs)
    rows.append(
        Row(
            section,
            f"16 units: RSS growth over {growth_secs} s",
            g["rss_growth_mb"],
            0.0,
            "MB",
            "<2 MB (10-min run: --long)",
            g["rss_growth_mb"] < 2,
        )
    )

    # everything on (4 units, the bridge, MCAP, CSV, a TUI on the plots tab), after warm-up;
    # the 10-minute figure with --long (the MCAP chunk index grows with the recording's
    # length by design: docs/recording.md)
    mem_secs = 600.0 if a.long else (20.0 if a.quick else 120.0)
    mem = attached.memory(mem_secs)
    rows.append(
        Row(
            section,
            f"everything on, 4 units: RSS growth over {mem_secs:g} s after 30 s",
            mem["rss_growth_mb"],
            mem["rss_start_mb"],
            "MB",
            "<=1 MB (10-min run: --long)",
            mem["rss_growth_mb"] <= 1,
        )
    )

    # 5. planner accuracy
    section = "5. planner accuracy (abh3 check vs the simulated wire)"
    planned, measured = bus_model.planner_accuracy()
    rows.append(
        Row(
            section,
            "8 units @100 Hz + polls, 500 kbit/s: planned vs measured load",
            planned,
            measured,
            "%",
            "within 5%",
            abs(planned - measured) / measured <= 0.05,
        )
    )

    # 6. the ROS 2 bridge (needs the ros2 extra)
    section = "6. ROS 2 bridge over DDS, loopback (baseline: the same in-process)"
    if importlib.util.find_spec("cyclonedds") is None:
        print("section 6 skipped: pip install -e '.[ros2]' for the ROS 2 bridge figures")
    else:
        logging.disable(logging.WARNING)  # the bridge's start-up notice, once per run
        lat = [ros2_bridge.vel_cmd_latency(100, seconds) for _ in range(runs)]
        for pct in ("50", "99"):
            rows.append(
                Row(
                    section,
                    f"1 unit @100 Hz: vel_cmd from another process to frame p{pct}",
                    med(lat, f"latency_p{pct}_ms"),
                    med(one, f"latency_p{pct}_ms"),
                    "ms",
                    "<=12 ms (cycle + 2)" if pct == "99" else "",
                    med(lat, "latency_p99_ms") <= 12 if pct == "99" else None,
                )
            )
        without = statistics.median(
            ros2_bridge.cpu_percent(8, 100, seconds, bridge=False) for _ in range(runs)
        )
        bridged = statistics.median(
            ros2_bridge.cpu_percent(8, 100, seconds, bridge=True) for _ in range(runs)
        )
        rows.append(
            Row(
                section,
                "8 units @100 Hz: CPU % of one core, bridge publishing vs none",
                bridged,
                without,
                "%",
                "<=1.5x",
                bridged <= 1.5 * without,
            )
        )
        logging.disable(logging.NOTSET)

    # 7. bursts of clients on the control socket, from a CAN recording
    section = "7. control-socket bursts (demo: 2 units at 50 Hz, recorded; baseline: 1 period)"
    cycles = 500 if a.quick else 3000
    worst = statistics.median(bursts.measure(200, cycles).worst_gap_periods for _ in range(runs))
    rows.append(
        Row(
            section,
            f"200 clients at once + {cycles} connect/close: worst DP0 gap",
            worst,
            1.0,
            "periods",
            "<=1.5 periods",
            worst <= 1.5,
        )
    )

    # 8. the e-stop does not wait for the schedule (issue 29 item 4)
    rows += estop.rows(10 if a.quick else 50, runs)

    # 9. a robot's twist, decided once for all its drives (issue 30)
    rows += robot.rows(2_000 if a.quick else 20_000, runs)

    # 10. the supervisor alone, its drives in `abh3 simulate` (issue 32 item 4); skipped,
    # with the reason, where no network namespace can be made
    rows += alone.rows(2.0 if a.quick else 10.0, runs, sizing=not a.quick)

    # 11. what an .mcap recording costs the bus loop against a .log (issue 34 item 2)
    rows += recording.rows(2.0 if a.quick else 10.0, runs if a.quick else max(runs, 5))

    # 12. a small computer's budget: the supervisor in a CPU cgroup (issue 34 items 1, 5);
    # skipped, with the reason, where no cgroup or namespace can be made
    rows += small.rows(2.0 if a.quick else 10.0, runs, sizing=not a.quick)

    # 13. the bus loop's Python calls per period, counted (issue 50); skipped, with the
    # reason, where no network namespace can be made
    if (why := netns.unavailable()) is None:
        rows += calls.rows(runs)
    else:
        print(f"{calls.SECTION}: not measured: {why}")

    print_rows(rows)
    missed = [r for r in rows if r.ok is False]
    print(f"\n{len(rows)} figures, {len(missed)} target(s) missed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
