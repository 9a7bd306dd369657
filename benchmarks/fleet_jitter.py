"""The bus never notices the broker (issue 33): DP0 period jitter with the ``mqtt`` plugin
against a flooding fleet and against a broker that dies, next to the same run without it.

``python -m benchmarks.fleet_jitter [--seconds S] [--runs N]`` (needs mosquitto and openssl, as the
tests do): 2 simulated units at 100 Hz with the bus loop's priority as ``abh3 run`` sets
it; the jitter is |interval − period| of each unit's DP0 commands as our pump sends them
(benchmarks/cycle_timing.py's probe). Scenarios: ``none`` (no plugin); ``flood, no
plugin`` (the flood below on this machine, nobody of ours subscribed: what the machine's
load alone does); ``flood`` (a fleet client in a process of its own publishes refused
e-stops as fast as it can and a 10 MB message every second, over MQTT 3.1.1 so that they
arrive; ``FJ_PROTOCOL=5``, ``FJ_BIG=0`` vary it); ``flood, plugin threads normal`` (the
same, the plugin's threads left at normal priority: as before it asked to run below the
loop); ``dead, no plugin`` (the broker killed at a third of the run and started again at
two thirds, nobody of ours connected: what the broker's death and start cost the machine);
``dead`` (the same, the plugin connected: it loses the broker and reconnects). Each
scenario's ratio is to its own baseline, the same run without MQTT, within each run.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.fleet import payloads
from abh3_supervisor.fleet.topics import Topics
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.priority import Priority, bus_priority
from abh3_supervisor.scheduler.stats import percentile
from benchmarks.cycle_timing import HOST, TxProbe
from tests.support.mosquitto import FLEET, Broker, password, running
from tests.support.mqtt_watch import Watcher

During = Callable[[threading.Event, float], None]  # what happens to the broker meanwhile
PROTOCOL = os.environ.get("FJ_PROTOCOL", "3.1.1")
BIG = os.environ.get("FJ_BIG", "1") == "1"
RATE = 100.0
UNITS = 2


def config(channel: str, broker: Broker | None, secret: Path) -> Config:
    units = "".join(
        f"  - {{name: u{i}, bus: b, abh3_id: {i + 1}, host_id: {HOST}, command_rate_hz: {RATE},"
        f" broadcast: {{mask: 0x7F, rate_hz: 10}}}}\n"
        for i in range(UNITS)
    )
    text = (
        f"buses:\n  b: {{interface: virtual, channel: {channel}, simulate: true}}\nunits:\n{units}"
    )
    if broker is not None:
        text += (
            f"plugins:\n  mqtt: {{broker: '{broker.url}', name: bench, username: bench,"
            f" password_file: '{secret}', protocol: '{PROTOCOL}', state_rate_hz: 10}}\n"
        )
    return parse_config(text, "fleet-bench.yaml")


def jitter(probe: TxProbe) -> tuple[float, float]:
    period, out = 1.0 / RATE, []
    for i in range(UNITS):
        times = [t for t, _ in probe.sent[ids.dp0_command_id(i + 1, HOST)]]
        times = times[len(times) // 10 :]  # skip the start-up
        out += [abs((b - a) - period) for a, b in itertools.pairwise(times)]
    return 1000 * (percentile(out, 50) or 0.0), 1000 * (percentile(out, 99) or 0.0)


def measure(
    cfg: Config, seconds: float, during: During | None = None, below_loop: bool = True
) -> tuple[float, float]:
    """``below_loop=False``: the plugin's threads at normal priority, as before it asked
    (``abh3_threads``), to show what asking changes."""
    probe = TxProbe()
    host = PluginHost(cfg)
    if not below_loop:
        host._threads_below_loop = lambda name: False  # type: ignore[method-assign]

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host) as rt:
            rt.pumps["b"].recorder = probe
            stop = threading.Event()
            worker = threading.Thread(target=during, args=(stop, seconds)) if during else None
            if worker is not None:
                worker.start()
            await asyncio.sleep(seconds)
            stop.set()
            if worker is not None:
                await asyncio.to_thread(worker.join)

    with bus_priority(Priority.AUTO):
        asyncio.run(scenario())
    return jitter(probe)


def flood_from_here(port: int, seconds: float) -> None:
    """The flooding fleet client, in a process of its own (its Python is not ours)."""
    broker = Broker(Path("/nonexistent"), {}, port=port)
    fleet = Watcher(broker, FLEET, client_id="bench-flood")
    assert fleet.connected()
    topic = Topics(os.environ.get("FJ_TARGET", "bench-u0")).command("estop")
    seq, next_big, end = 0, 0.0, time.monotonic() + seconds
    while time.monotonic() < end:
        seq += 1
        body = payloads.estop_command(seq, time.time(), sender="flood", reason="x")
        fleet.client.publish(topic, json.dumps(body), 0)
        if BIG and time.monotonic() >= next_big:
            fleet.client.publish(topic, b"{" + b"x" * 10_000_000, 0)
            next_big = time.monotonic() + 1.0
        if seq % 200 == 0:
            time.sleep(0.001)  # let paho's thread write: a flood, not a spin on its lock
    fleet.close()


def flood(broker: Broker) -> During:
    def run(stop: threading.Event, seconds: float) -> None:
        args = ["--flood", str(broker.port), "--seconds", str(seconds)]
        flooder = subprocess.Popen([sys.executable, "-m", "benchmarks.fleet_jitter", *args])
        stop.wait(seconds + 5)
        flooder.wait(30)

    return run


def dead(broker: Broker) -> During:
    def run(stop: threading.Event, seconds: float) -> None:
        stop.wait(seconds / 3)
        broker.stop(signal.SIGKILL)
        stop.wait(seconds / 3)
        broker.start()

    return run


SCENARIOS = {  # name → its baseline: the same run without MQTT
    "none": "none",
    "flood, no plugin": "none",
    "flood": "flood, no plugin",
    "flood, plugin threads normal": "flood, no plugin",
    "dead, no plugin": "none",
    "dead": "dead, no plugin",
}


def one_run(broker: Broker, secret: Path, seconds: float) -> dict[str, tuple[float, float]]:
    return {
        "none": measure(config("fj-none", None, secret), seconds),
        # the same flood on this machine (its client and the broker busy), no plugin
        "flood, no plugin": measure(config("fj-fnone", None, secret), seconds, flood(broker)),
        "flood": measure(config("fj-flood", broker, secret), seconds, flood(broker)),
        "flood, plugin threads normal": measure(
            config("fj-fnorm", broker, secret), seconds, flood(broker), below_loop=False
        ),
        # the broker killed and started again on this machine, nobody of ours connected
        "dead, no plugin": measure(config("fj-dnone", None, secret), seconds, dead(broker)),
        "dead": measure(config("fj-dead", broker, secret), seconds, dead(broker)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--runs", type=int, default=3, help="interleaved; medians printed")
    parser.add_argument("--flood", type=int, help=argparse.SUPPRESS)  # the flooder's port
    args = parser.parse_args()
    if args.flood:
        flood_from_here(args.flood, args.seconds)
        return
    runs: list[dict[str, tuple[float, float]]] = []
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        secret = Path(tmp) / "pw"
        secret.write_text(password("bench"))
        with running(Path(tmp) / "broker", {"bench": ["bench-u0", "bench-u1"]}) as broker:
            for _ in range(args.runs):  # every scenario once per run: the machine's drift
                runs.append(one_run(broker, secret, args.seconds))  # is shared by all
    print(
        f"DP0 period jitter, {UNITS} units at {RATE:g} Hz, {args.seconds:g} s each, "
        f"median of {args.runs} interleaved run(s) [min–max]"
    )
    for name, baseline in SCENARIOS.items():
        p50 = statistics.median(r[name][0] for r in runs)
        p99s = [r[name][1] for r in runs]
        ratios = [r[name][1] / r[baseline][1] for r in runs]  # within each run
        print(
            f"  {name:28} p50 {p50:6.3f} ms  p99 {statistics.median(p99s):6.3f} ms "
            f"[{min(p99s):.3f}–{max(p99s):.3f}]  {statistics.median(ratios):5.2f}x "
            f"[{min(ratios):.2f}–{max(ratios):.2f}] {baseline}"
        )


if __name__ == "__main__":
    main()
