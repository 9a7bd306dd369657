"""8. The e-stop's latency: an ``estop`` request on the control socket → the first stop frame.

A supervisor on one simulated unit (in this process, its bus loop at the priority ``abh3 run``
gives it) serves its control socket. A client in a process of its own, as ``abh3 estop`` or a
script would be, arms the unit (``SERVO ON ON``, ``START ON ON``, ``VEL 300 0``), lets the armed
frames go out for a random 2–3 command periods (so the request falls anywhere in the period),
sends ``estop``, then ``clear_estop``, and repeats. A python-can ``virtual`` bus on the same
channel sees every frame with the time python-can stamped it in ``send`` (``time.time()``, the
clock the client stamps its request with just before writing it). The figure, per e-stop: from
the request to the first DP0 command with START off and zero setpoints. The motion gate sends
that frame at once (docs/safety.md), so it should not depend on the command rate; the baseline
printed next to it is one command period, what waiting for the schedule would cost at worst.

Run alone: ``python -m benchmarks.estop [--count N] [--runs N]`` (both rates).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

import can

from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.priority import Priority, bus_priority
from abh3_supervisor.scheduler.stats import percentile
from abh3_supervisor.service.server import ControlServer
from benchmarks.report import Row, machine, print_rows

ROOT = Path(__file__).resolve().parent.parent  # where `benchmarks` imports from
ABH3, HOST, UNIT = 1, 100, "u0"
ARM = ("SERVO ON ON", "START ON ON", "VEL 300 0")


def config(rate: float, channel: str) -> Config:
    text = (
        f"buses:\n  b: {{interface: virtual, channel: {channel}, simulate: true}}\n"
        f"units:\n  - {{name: {UNIT}, bus: b, abh3_id: {ABH3}, host_id: {HOST}, "
        f"command_rate_hz: {rate}}}\n"
    )
    return parse_config(text, "estop-bench.yaml")


def client(path: Path, count: int, period: float) -> list[float]:
    """The client's side (its own process): arm, wait, e-stop, clear; the request times."""
    rng = random.Random(1)
    sent: list[float] = []
    ctl = ControlClient(path)
    try:
        ctl.call("hello", name="estop-bench")
        for _ in range(count):
            for text in ARM:
                answer = ctl.call("command", unit=UNIT, text=text)
                if answer["response"] != "":
                    raise RuntimeError(f"{text!r} answered {answer['response']!r}")
            time.sleep(rng.uniform(2, 3) * period)  # the workload: armed frames, a random phase
            sent.append(time.time())
            ctl.call("estop")
            ctl.call("clear_estop")
    finally:
        ctl.close()
    return sent


def latencies(
    wire: list[can.Message], requests: list[float], start_bits: int
) -> tuple[list[float], int]:
    """Per request, seconds to the first stop frame after it; and how many requests found
    the unit not armed (its last frame before the request had START off or zero motion)."""
    command = ids.without_priority(ids.dp0_command_id(ABH3, HOST))
    dp0 = [
        (msg.timestamp, frames.unpack_dp0_command(bytes(msg.data)))
        for msg in wire
        if ids.without_priority(msg.arbitration_id) == command
    ]
    found: list[float] = []
    unarmed = 0
    for t0 in requests:
        before = [fields for ts, fields in dp0 if ts < t0]
        if not before or not (before[-1][2] & start_bits and before[-1][0]):
            unarmed += 1
            continue
        stop = next(
            (
                ts
                for ts, (ay, bx, inputs) in dp0
                if ts >= t0 and not (ay or bx or inputs & start_bits)
            ),
            None,
        )
        if stop is None:
            raise RuntimeError(f"no stop frame after the e-stop requested at {t0:.6f}")
        found.append(stop - t0)
    return found, unarmed


def measure(rate: float, count: int) -> dict[str, float]:
    """``count`` e-stops at ``rate`` Hz: p50/p99/max in ms, the samples and unarmed count."""
    channel = f"estop-bench-{os.getpid()}-{rate:g}"
    cfg = config(rate, channel)
    host = PluginHost(cfg)
    wire = can.Bus(interface="virtual", channel=channel)  # read after the run: stamped on send
    requests: list[float] = []
    start_bits = 0

    async def scenario(path: Path) -> None:
        nonlocal start_bits
        async with Runtime(cfg, plugins=host) as rt:
            start_bits = rt.supervisor.unit(UNIT).layout.start.both
            server = ControlServer(rt, host, path)
            await server.start()
            try:
                proc = await asyncio.create_subprocess_exec(
                    sys.executable,
                    "-m",
                    "benchmarks.estop",
                    "--client",
                    str(path),
                    "--rate",
                    str(rate),
                    "--count",
                    str(count),
                    stdout=asyncio.subprocess.PIPE,
                    cwd=ROOT,
                )
                out, _ = await proc.communicate()
                if proc.returncode != 0:
                    raise RuntimeError(f"the e-stop client ended with {proc.returncode}")
                requests.extend(json.loads(out))
            finally:
                await server.close()

    try:
        with tempfile.TemporaryDirectory(dir="/tmp") as tmp, bus_priority(Priority.AUTO):
            asyncio.run(scenario(Path(tmp) / "s" / "estop.sock"))
        seen: list[can.Message] = []
        while (msg := wire.recv(0)) is not None:
            seen.append(msg)
    finally:
        wire.shutdown()
    found, unarmed = latencies(seen, requests, start_bits)
    if not found:
        raise RuntimeError(f"none of {count} e-stops found the unit armed")
    ms = [1000 * s for s in found]
    return {
        "p50_ms": percentile(ms, 50) or 0.0,
        "p99_ms": percentile(ms, 99) or 0.0,
        "max_ms": max(ms),
        "samples": float(len(ms)),
        "unarmed": float(unarmed),
    }


def rows(count: int, runs: int) -> list[Row]:
    """The benchmark's section: p50/p99/max at 10 and 100 Hz, medians of ``runs``."""
    section = "8. e-stop: request → first stop frame on the wire (baseline: 1 period)"
    out: list[Row] = []
    for rate in (10, 100):
        figures = [measure(rate, count) for _ in range(runs)]
        for stat, target in (("p50", ""), ("p99", "<=2 ms"), ("max", "")):
            value = statistics.median(f[f"{stat}_ms"] for f in figures)
            out.append(
                Row(
                    section,
                    f"{rate:>3} Hz, {count} e-stops over the socket: {stat}",
                    value,
                    1000 / rate,
                    "ms",
                    target,
                    value <= 2 if target else None,
                )
            )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.estop", description=__doc__)
    p.add_argument("--rate", type=float, default=100.0, help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, default=50, help="e-stops per rate (default 50)")
    p.add_argument("--runs", type=int, default=1, help="repetitions; the median is printed")
    p.add_argument("--client", type=Path, help=argparse.SUPPRESS)  # the client's own process
    a = p.parse_args(argv)
    if a.client is not None:
        print(json.dumps(client(a.client, a.count, 1 / a.rate)))
        return 0
    print(f"machine: {machine()}")
    print_rows(rows(a.count, a.runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
