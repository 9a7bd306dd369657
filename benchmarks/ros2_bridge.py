"""6. The ROS 2 bridge over DDS on loopback: what the network path adds.

- ``vel_cmd`` to frame: a separate process publishes ``vel_cmd`` at random moments (as a
  teleop node does); we time each value until the first command frame that carries it
  leaves the host. Both processes stamp with CLOCK_MONOTONIC (``perf_counter`` on Linux),
  which is system-wide. Baseline: the same setpoint changes made in-process
  (section 3's input-to-frame figure, same rate).
- CPU: this process's CPU share with the bridge publishing every unit's feedback and
  status, against the same run without the bridge.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Config
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.scheduler.stats import percentile
from benchmarks.cycle_timing import TxProbe

DOMAIN = 77
# the publishing peer: waits to be matched, then writes values 1, 2, … at random moments
PEER = """
import json, random, sys, time
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from abh3_plugins.ros2.dds import qos
from abh3_plugins.ros2.settings import QosSettings
from abh3_plugins.ros2.types import Abh3Velocity
dp = DomainParticipant(int(sys.argv[1]))
w = DataWriter(dp, Topic(dp, "rt/u0/vel_cmd", Abh3Velocity), qos=qos(QosSettings()))
while not w.get_matched_subscriptions():
    time.sleep(0.05)
time.sleep(0.5)
rng, sent, value = random.Random(1), [], 0
end = time.perf_counter() + float(sys.argv[2])
while time.perf_counter() < end:
    time.sleep(rng.uniform(0.005, 0.03))
    value += 1
    t = time.perf_counter()
    w.write(Abh3Velocity(value * 0.2, 0.0))
    sent.append((t, value))
print(json.dumps(sent))
"""


def _loopback() -> None:
    from abh3_plugins.ros2.dds import LOOPBACK_URI  # cyclonedds: only with the ros2 extra

    os.environ["CYCLONEDDS_URI"] = LOOPBACK_URI


def setup(units: int, rate: float, channel: str, bridge: bool) -> tuple[Config, PluginHost]:
    """The configuration as a user writes it, with the ros2 plugin or without."""
    listed = "".join(
        f"  - {{name: u{i}, abh3_id: {i + 10}, command_rate_hz: {rate}, "
        "broadcast: {mask: 0x7f, rate_hz: 10}}\n"
        for i in range(units)
    )
    text = f"buses: {{b: {{interface: virtual, channel: {channel}, simulate: true}}}}\n"
    text += f"units:\n{listed}"
    if bridge:
        text += f"plugins: {{ros2: {{domain_id: {DOMAIN}, allow_commands: true}}}}\n"
    cfg = parse_config(text, "bench.yaml")
    return cfg, PluginHost(cfg)


def vel_cmd_latency(rate: float, seconds: float) -> dict[str, float]:
    """p50/p99 [ms] from a vel_cmd written in another process to the frame carrying it."""
    _loopback()
    cfg, host = setup(1, rate, "ros2-latency", bridge=True)
    probe = TxProbe()

    async def scenario() -> list[tuple[float, int]]:
        async with Runtime(cfg, plugins=host) as rt:
            rt.pumps["b"].recorder = probe
            sup = rt.supervisor
            for name in sup.units:  # switched on and reported so: the vel_cmd moves it
                for text in ("SERVO ON ON", "START ON ON"):
                    assert await sup.command(name, text) == ""
            while any(sup.robot_unready(name) is not None for name in sup.units):
                await asyncio.sleep(0.01)
            peer = await asyncio.create_subprocess_exec(
                sys.executable, "-c", PEER, str(DOMAIN), str(seconds), stdout=subprocess.PIPE
            )
            out, _ = await peer.communicate()
            await asyncio.sleep(0.05)
            return [(float(t), int(v)) for t, v in json.loads(out)]

    sent = asyncio.run(scenario())
    frames_out = probe.sent[ids.dp0_command_id(10, 2)]
    latencies = []
    for t, value in sent:
        payload = frames.encode_dp0_command(value, 0, 0)[:4]  # the velocity fields
        first = next((ts for ts, data in frames_out if ts >= t and data[:4] == payload), None)
        if first is not None:
            latencies.append(first - t)
    return {
        "latency_p50_ms": 1000 * (percentile(latencies, 50) or 0.0),
        "latency_p99_ms": 1000 * (percentile(latencies, 99) or 0.0),
        "delivered_percent": 100 * len(latencies) / max(1, len(sent)),
    }


def cpu_percent(units: int, rate: float, seconds: float, bridge: bool) -> float:
    """This process's CPU share running ``units`` at ``rate``, with or without the bridge."""
    _loopback()
    cfg, host = setup(units, rate, f"ros2-cpu-{bridge}", bridge)

    async def scenario() -> float:
        async with Runtime(cfg, plugins=host):
            await asyncio.sleep(1.0)  # warm up
            cpu0, wall0 = time.process_time(), time.perf_counter()
            await asyncio.sleep(seconds)
            return 100 * (time.process_time() - cpu0) / (time.perf_counter() - wall0)

    return asyncio.run(scenario())
