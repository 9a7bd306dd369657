"""3. Cycle timing in real time: 8 simulated units at 100 Hz on the virtual bus.

Measures, per unit, the achieved command rate against the requested one, the jitter of
the command period (|interval − period|, p50/p99 over all units), and the input-to-frame
latency: a setpoint is changed at random moments and timed until the first frame that
carries it leaves the host. Baseline: the same run with one unit (no contention).
"""

from __future__ import annotations

import asyncio
import itertools
import random
import time
from collections import defaultdict
from collections.abc import Callable

import can

from abh3_supervisor.clients.tui.app import SupervisorApp, TuiSource
from abh3_supervisor.config.model import BroadcastConfig, BusConfig, Config, SimConfig, UnitConfig
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.thread import RuntimeThread
from abh3_supervisor.scheduler.stats import percentile


class TxProbe(can.Listener):
    """Sees every frame our pump sends (as the recorder would) with a monotonic time."""

    def __init__(self) -> None:
        self.sent: dict[int, list[tuple[float, bytes]]] = defaultdict(list)

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_rx:
            self.sent[msg.arbitration_id].append((time.perf_counter(), bytes(msg.data)))


def config(n: int, rate: float, channel: str) -> Config:
    units = {
        f"u{i}": UnitConfig(
            name=f"u{i}",
            bus="b",
            abh3_id=i + 1,
            command_rate_hz=rate,
            broadcast=BroadcastConfig(mask=0x7F, rate_hz=10),
        )
        for i in range(n)
    }
    bus = BusConfig(name="b", interface="virtual", channel=channel, simulate=SimConfig())
    return Config(file="bench", buses={"b": bus}, units=units)


def run(n: int, rate: float, seconds: float, channel: str, tui: bool = False) -> dict[str, float]:
    """Measure; with ``tui`` the Textual app runs (headless, refreshing at 10 Hz) alongside."""
    cfg = config(n, rate, channel)
    probe = TxProbe()
    latencies: list[float] = []
    host = PluginHost(cfg)
    source = TuiSource(tuple(cfg.units))
    if tui:
        host.add_source(source)

    async def measure(rt: Runtime, call: Callable[..., object]) -> None:
        rt.pumps["b"].recorder = probe
        sup = rt.supervisor
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
            call(sup.set_velocity, f"u{unit}", value * 0.2, 0.0)
        await asyncio.sleep(0.05)
        for t, abh3, payload in pending:
            sent = probe.sent[ids.dp0_command_id(abh3, 2)]
            first = next((ts for ts, data in sent if ts >= t and data == payload), None)
            if first is not None:
                latencies.append(first - t)

    async def scenario() -> None:
        if not tui:
            async with Runtime(cfg, plugins=host) as rt:
                await measure(rt, lambda fn, *args: fn(*args))
            return
        # as `abh3 run` does with a terminal: the buses on their own thread, the app here
        bridge = RuntimeThread(cfg, record=None, plugins=host)
        rt = bridge.start()
        app = SupervisorApp(rt, source, bridge)
        app_task = asyncio.ensure_future(app.run_async(headless=True, size=(160, 50)))
        try:
            await measure(rt, bridge.call)
        finally:
            app.exit()
            await app_task
            bridge.stop()

    asyncio.run(scenario())
    period = 1.0 / rate
    jitter: list[float] = []
    rates: list[float] = []
    for i in range(n):
        times = [t for t, _ in probe.sent[ids.dp0_command_id(i + 1, 2)]]
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
