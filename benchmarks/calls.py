"""13. Python calls per bus period: what the bus loop does, counted, not timed.

A count does not move with this VM's speed as a CPU figure does. Four units at 100 Hz
(:mod:`benchmarks.alone`'s robot: the drives in ``abh3 simulate`` on ``udp_multicast``
in a network namespace whose only interface is ``lo``): every Python function call
(``sys.setprofile``'s ``call``) and every call of a builtin (``c_call``) on the bus
loop's thread, over a window after warm-up, divided by the periods in it — one period
is four DP0 exchanges. The baseline is :func:`benchmarks.alone.bare` (a bare
python-can host: build, send, receive each exchange, its own frames dropped in the
kernel as ours are) counted the same way. Rows: the supervisor alone; with an ``.mcap``
recording and the control socket; with the ROS 2 bridge too (when installed).

Threads other than the loop's (the recorder's writer, the plugins' workers) are not in
the count: what they cost shows in section 12's CPU figures. ``python -m
benchmarks.calls`` prints this section.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks import alone, small
from benchmarks.report import Row, machine, print_rows

SECTION = "13. Python calls per bus period (4 units @100 Hz: four DP0 exchanges a period)"
TARGET = 300  # Python calls per period (issue 50)
WARMUP_S, WINDOW_S = 2.0, 4.0


class Counter:
    """``call`` and ``c_call`` events of the thread it is installed on, while on."""

    def __init__(self) -> None:
        self.on = False
        self.py = self.c = 0

    def __call__(self, frame: Any, event: str, arg: Any) -> None:
        if self.on:
            if event == "call":
                self.py += 1
            elif event == "c_call":
                self.c += 1


def supervise(argv: list[str]) -> None:
    """``abh3 run`` with its loop's calls counted: one JSON line on stdout at the end."""
    import asyncio

    from abh3_supervisor.clients import cli
    from abh3_supervisor.scheduler import pump

    counter = Counter()
    result: dict[str, float] = {}
    start = pump.BusPump.start

    def started(self: pump.BusPump) -> None:  # the first pump: the window after warm-up
        if not result:
            loop = asyncio.get_running_loop()
            result["armed"] = 1.0

            def on() -> None:
                counter.py = counter.c = 0
                counter.on, result["t0"] = True, loop.time()

            def off() -> None:
                counter.on, result["t1"] = False, loop.time()
                result["py"], result["c"] = counter.py, counter.c

            loop.call_later(WARMUP_S, on)
            loop.call_later(WARMUP_S + WINDOW_S, off)
        start(self)

    pump.BusPump.start = started  # type: ignore[method-assign]
    sys.setprofile(counter)
    try:
        cli.main(argv)
    finally:
        sys.setprofile(None)
    print(json.dumps(result), flush=True)


def bare(units: int, rate: float) -> None:
    """:func:`benchmarks.alone.bare` with its calls counted over the window."""
    counter = Counter()
    result: dict[str, float] = {}

    def window() -> None:
        time.sleep(WARMUP_S)
        counter.py = counter.c = 0
        t0 = time.monotonic()
        counter.on = True
        time.sleep(WINDOW_S)
        counter.on = False
        result.update(t0=t0, t1=time.monotonic(), py=counter.py, c=counter.c)
        os.kill(os.getpid(), 15)  # alone.bare ends at SIGTERM

    threading.Thread(target=window, daemon=True).start()
    sys.setprofile(counter)  # this thread only: the bare host's loop
    try:
        alone.bare(units, rate)
    finally:
        sys.setprofile(None)
    print(json.dumps(result), flush=True)


def _per_period(result: dict[str, float], rate: float) -> tuple[float, float]:
    periods = (result["t1"] - result["t0"]) * rate
    return result["py"] / periods, result["c"] / periods


MCAP_ROW = "+ .mcap recording, control socket, status polls"


def counts(runs: int = 1, only: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
    """Each run's rows: {label: (py, c) per period}, the bare host first (``only``: those
    rows of the supervisor's and no bare host)."""
    from abh3_supervisor.runtime import netns

    bridge = small.bridge_available() is None
    out: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(dir="/tmp") as name, netns.Namespace() as ns:
        tmp = Path(name)
        plain = tmp / "alone.yaml"
        plain.write_text(alone.config(alone.UNITS, alone.RATE, "udp_multicast"))
        robot = tmp / "robot.yaml"
        robot.write_text(small.config(alone.UNITS, alone.RATE, bridge=bridge))
        polled = tmp / "polled.yaml"  # the same without the bridge: the drives' file too
        polled.write_text(small.config(alone.UNITS, alone.RATE, bridge=False))
        sim = ns.popen(
            [sys.executable, "-m", "abh3_supervisor", "simulate", str(polled)],
            cwd=alone.ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            if not alone._line(sim, "abh3 simulate").startswith("ready: bus b"):
                raise RuntimeError("abh3 simulate did not get its drives ready")
            runs_of = {
                "supervisor alone": [str(plain), "--no-socket"],
                MCAP_ROW: [
                    str(polled), "--record", str(tmp / "r.mcap"), "--socket", str(tmp / "s.sock"),
                ],
            }  # fmt: skip
            if bridge:
                runs_of["+ the ROS 2 bridge (DDS)"] = [
                    str(robot), "--record", str(tmp / "b.mcap"), "--socket", str(tmp / "b.sock"),
                ]  # fmt: skip
            for _ in range(runs):
                row: dict[str, Any] = {} if only else {"bare": _child(ns, ["bare"])}
                for label, args in runs_of.items():
                    if only and label not in only:
                        continue
                    argv = ["run", *args, "--headless", "--status-interval", "0",
                            "--duration", f"{WARMUP_S + WINDOW_S + 1:g}"]  # fmt: skip
                    row[label] = _child(ns, ["supervise", *argv])
                out.append(row)
        finally:
            alone._stop(sim)
    return out


def _child(ns: Any, argv: list[str]) -> tuple[float, float]:
    proc = ns.run(
        [sys.executable, "-m", "benchmarks.calls", *argv],
        cwd=alone.ROOT, capture_output=True, timeout=120,
    )  # fmt: skip
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if not lines or "py" not in (result := json.loads(lines[-1])):
        raise RuntimeError(f"benchmarks.calls {argv[0]}: no count:\n{proc.stderr[-2000:]}")
    return _per_period(result, alone.RATE)


def rows(runs: int = 1) -> list[Row]:
    measured = counts(runs)
    import statistics

    def spread(values: list[float]) -> str:
        return f"runs {min(values):.0f}–{max(values):.0f}" if len(values) > 1 else "1 run"

    bare_py = [r["bare"][0] for r in measured]
    bare_c = [r["bare"][1] for r in measured]
    out: list[Row] = []
    for label in measured[0]:
        if label == "bare":
            continue
        py = [r[label][0] for r in measured]
        c = [r[label][1] for r in measured]
        out.append(
            Row(SECTION, f"{label}: Python calls", statistics.median(py),
                statistics.median(bare_py), "/period",
                f"<={TARGET}; {spread(py)}; baseline {spread(bare_py)}",
                statistics.median(py) <= TARGET)
        )  # fmt: skip
        out.append(
            Row(SECTION, "  calls of builtins", statistics.median(c), statistics.median(bare_c),
                "/period", f"{spread(c)}; baseline {spread(bare_c)}")
        )  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m benchmarks.calls", description=__doc__)
    p.add_argument("--runs", type=int, default=3, help="repetitions; the median is printed")
    sub = p.add_subparsers(dest="role")
    sub.add_parser("bare", help="the bare python-can host, counted (in the namespace)")
    s = sub.add_parser("supervise", help="abh3 run, counted (in the namespace)")
    s.add_argument("argv", nargs=argparse.REMAINDER)
    a = p.parse_args(argv)
    if a.role == "bare":
        bare(alone.UNITS, alone.RATE)
    elif a.role == "supervise":
        supervise(a.argv)
    else:
        if (why := _unavailable()) is not None:
            print(f"{SECTION}: not measured: {why}")
            return
        print(f"machine: {machine()}")
        print_rows(rows(a.runs))


def _unavailable() -> str | None:
    from abh3_supervisor.runtime import netns

    return netns.unavailable()


if __name__ == "__main__":
    main()
