"""3. Cycle timing in real time: 8 simulated units at 100 Hz on the virtual bus.

Measures, per unit, the achieved command rate against the requested one, the jitter of
the command period (|interval − period|, p50/p99 over all units), and the input-to-frame
latency: a setpoint is changed at random moments and timed until the first frame that
carries it leaves the host. Baseline: the same run with one unit (no contention).
With ``tuis`` the supervisor serves its control socket and that many TUIs attach from
processes of their own (headless Textual, state at 10 Hz, cycling tabs), as operators'
would.
"""

from __future__ import annotations

import asyncio
import itertools
import random
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import can

from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.priority import Priority, bus_priority
from abh3_supervisor.scheduler.stats import percentile
from abh3_supervisor.service.server import ControlServer


class TxProbe(can.Listener):
    """Sees every frame our pump sends (as the recorder would) with a monotonic time."""

    def __init__(self) -> None:
        self.sent: dict[int, list[tuple[float, bytes]]] = defaultdict(list)

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_rx:
            self.sent[msg.arbitration_id].append((time.perf_counter(), bytes(msg.data)))


HOST = 100  # above every unit's abh3_id


def config(n: int, rate: float, channel: str) -> Config:
    """As a YAML file would say it: clients of the socket rebuild it from the text."""
    units = "".join(
        f"  - {{name: u{i}, bus: b, abh3_id: {i + 1}, host_id: {HOST}, command_rate_hz: {rate},"
        f" broadcast: {{mask: 0x7F, rate_hz: 10}}}}\n"
        for i in range(n)
    )
    text = (
        f"buses:\n  b: {{interface: virtual, channel: {channel}, simulate: true}}\nunits:\n{units}"
    )
    return parse_config(text, "bench.yaml")


class _Input(InputSource):
    """A unit's input (a plugin's would be one): its commands reach the loop through its
    feed, as every input's do."""

    def __init__(self, unit: str) -> None:
        super().__init__(f"bench:{unit}", (unit,))
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None


def run(n: int, rate: float, seconds: float, channel: str, tuis: int = 0) -> dict[str, float]:
    """Measure; with ``tuis`` that many TUIs are attached from other processes."""
    cfg = config(n, rate, channel)
    probe = TxProbe()
    latencies: list[float] = []
    host = PluginHost(cfg)

    async def measure(rt: Runtime) -> None:
        rt.pumps["b"].recorder = probe
        sup = rt.supervisor
        for name in sup.units:  # switched on, and reported so: every setpoint goes out
            for text in ("SERVO ON ON", "START ON ON"):
                assert await sup.command(name, text) == ""
        while any(sup.robot_unready(name) is not None for name in sup.units):
            await asyncio.sleep(0.01)
        feeds: dict[str, InputFeed] = {}
        for name in sup.units:  # each unit's input, as a plugin's joins the arbitration
            feed = host.attach(_Input(name))
            assert feed is not None
            feeds[name] = feed
        end = time.perf_counter() + seconds
        rng = random.Random(1)
        value = 0
        pending: list[tuple[float, int, bytes]] = []
        while time.perf_counter() < end:
            await asyncio.sleep(rng.uniform(0.005, 0.03))  # input arrives at random moments
            value = value % 3000 + 1
            unit = rng.randrange(n)
            inputs = sup.units[f"u{unit}"].inputs
            pending.append(
                (time.perf_counter(), unit + 1, frames.encode_dp0_command(value, 0, inputs))
            )
            feeds[f"u{unit}"].velocity(value * 0.2, 0.0)  # on the loop at its next turn
        await asyncio.sleep(0.05)
        for t, abh3, payload in pending:
            sent = probe.sent[ids.dp0_command_id(abh3, HOST)]
            first = next((ts for ts, data in sent if ts >= t and data == payload), None)
            if first is not None:
                latencies.append(first - t)

    async def scenario(path: Path) -> None:
        async with Runtime(cfg, plugins=host) as rt:
            if not tuis:
                await measure(rt)
                return
            server = ControlServer(rt, host, path)
            await server.start()
            clients = [
                subprocess.Popen(
                    [sys.executable, "-m", "benchmarks.tui_client", str(path), str(seconds + 30)],
                    cwd=Path(__file__).resolve().parent.parent,  # where `benchmarks` imports
                )
                for _ in range(tuis)
            ]
            try:
                deadline = time.perf_counter() + 30
                while len(server.clients) < tuis:  # each attached
                    if any(c.poll() is not None for c in clients):
                        raise RuntimeError("a TUI client ended before it attached")
                    if time.perf_counter() > deadline:
                        raise RuntimeError("the TUI clients did not attach within 30 s")
                    await asyncio.sleep(0.05)
                await asyncio.sleep(1.0)  # their first screens drawn
                await measure(rt)
                if any(c.poll() is not None for c in clients):
                    raise RuntimeError("a TUI client ended during the measurement")
            finally:
                for client in clients:
                    client.terminate()
                    client.wait(10)
                await server.close()

    # the loop's priority as `abh3 run` sets it (--priority auto: real-time where allowed)
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp, bus_priority(Priority.AUTO):
        asyncio.run(scenario(Path(tmp) / "s" / "bench.sock"))
    period = 1.0 / rate
    jitter: list[float] = []
    rates: list[float] = []
    for i in range(n):
        times = [t for t, _ in probe.sent[ids.dp0_command_id(i + 1, HOST)]]
        times = times[len(times) // 10 :]  # skip the start-up
        jitter += [abs((b - a) - period) for a, b in itertools.pairwise(times)]
        rates.append((len(times) - 1) / (times[-1] - times[0]))
    return {
        "rate_error_percent": 100 * max(abs(r - rate) / rate for r in rates),
        "jitter_p50_ms": 1000 * (percentile(jitter, 50) or 0.0),
        "jitter_p99_ms": 1000 * (percentile(jitter, 99) or 0.0),
        "latency_p99_ms": 1000 * (percentile(latencies, 99) or 0.0),
        "latency_p50_ms": 1000 * (percentile(latencies, 50) or 0.0),
    }
