"""4. Scale and memory: units per bus, buses per process, RSS and its growth.

Each measurement runs in a fresh subprocess (``python -m benchmarks.scale …``) so its
resident set is its own. The baseline for memory is a Python process that has only
imported python-can; the baseline for CPU is the same run with one unit.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import time

from abh3_supervisor.config.model import BroadcastConfig, BusConfig, Config, SimConfig, UnitConfig
from abh3_supervisor.runtime.bus_runtime import Runtime


def rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def build(units: int, buses: int, rate: float, simulate: bool) -> Config:
    bus_cfgs = {
        f"b{j}": BusConfig(
            name=f"b{j}",
            interface="virtual",
            channel=f"scale{j}",
            simulate=SimConfig() if simulate else None,
        )
        for j in range(buses)
    }
    unit_cfgs = {}
    for j in range(buses):
        for i in range(units):
            name = f"b{j}u{i}"
            unit_cfgs[name] = UnitConfig(
                name=name,
                bus=f"b{j}",
                abh3_id=i + 1,
                command_rate_hz=rate,
                broadcast=BroadcastConfig(mask=0x7F, rate_hz=10),
            )
    return Config(file="bench", buses=bus_cfgs, units=unit_cfgs)


def measure(units: int, buses: int, rate: float, seconds: float) -> dict[str, float]:
    cfg = build(units, buses, rate, simulate=True)

    async def scenario() -> dict[str, float]:
        async with Runtime(cfg) as rt:
            await asyncio.sleep(min(10.0, seconds / 4))  # warm up: caches, deques full
            rss_start = rss_mb()
            cpu0, wall0 = time.process_time(), time.perf_counter()
            await asyncio.sleep(seconds - min(10.0, seconds / 4))
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
            now = rt.supervisor.clock()
            achieved = [
                slot.stats.achieved_rate_hz(now) / slot.stats.requested_rate_hz
                for sched in rt.supervisor.schedulers.values()
                for slot in sched.slots.values()
            ]
            return {
                "units": units * buses,
                "cpu_percent": 100 * cpu / wall,
                "min_rate_ratio": min(achieved),
                "rss_mb": rss_mb(),
                "rss_growth_mb": rss_mb() - rss_start,
            }

    return asyncio.run(scenario())


def baseline_rss() -> float:
    import can  # noqa: F401 - the baseline is a process with python-can loaded

    return rss_mb()


def in_subprocess(*args: str) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.scale", *args],
        capture_output=True,
        text=True,
        check=True,
        timeout=1200,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--units", type=int, default=1)
    p.add_argument("--buses", type=int, default=1)
    p.add_argument("--rate", type=float, default=50.0)
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--baseline", action="store_true")
    a = p.parse_args()
    if a.baseline:
        print(json.dumps({"rss_mb": baseline_rss()}))
    else:
        print(json.dumps(measure(a.units, a.buses, a.rate, a.seconds)))


if __name__ == "__main__":
    main()
