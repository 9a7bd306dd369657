"""The fleet at scale (issue 33): 20 supervisors × 2 simulated units, each an ``abh3 run
--headless`` process publishing to one Mosquitto on 127.0.0.1. A fresh fleet client sees
all 40 unit states within 2 s; an e-stop to ``all`` reaches every unit's stop frame on its
bus (read back from each supervisor's recording) with p99 ≤ 250 ms; a broker restart
reconnects everyone within 10 s with the retained state right again; one more supervisor
killed with -9 shows as connection broken within 1.5 × its keep-alive.

About 20 s on a 2-core machine (20 processes at 50 Hz per unit), in every full run;
``ABH3_FLEET_SCALE=0`` leaves it out, ``ABH3_FLEET_SCALE_N`` sets the count. It prints
its figures with ``-s`` (docs/performance.md, "Where the targets stand": the fleet row)."""

from __future__ import annotations

import contextlib
import os
import signal
import statistics
import time
from pathlib import Path

import pytest

from abh3_supervisor.fleet import payloads
from abh3_supervisor.fleet.topics import Topics
from tests.support.mosquitto import FLEET, running
from tests.support.mqtt_watch import Received, Watcher, config, stop_frames, supervisor

pytestmark = [
    pytest.mark.wallclock,
    pytest.mark.skipif(
        os.environ.get("ABH3_FLEET_SCALE") == "0", reason="ABH3_FLEET_SCALE=0: left out"
    ),
]
N = int(os.environ.get("ABH3_FLEET_SCALE_N", "20"))


def names() -> list[str]:
    return [f"s{i:02d}" for i in range(1, N + 1)]


def fresh(broker: object, tag: str) -> Watcher:
    w = Watcher(broker, FLEET, client_id=f"scale-{tag}-{time.monotonic_ns()}")  # type: ignore[arg-type]
    assert w.connected()
    return w


def states_seen(w: Watcher) -> set[str]:
    return {m.topic for m in w.messages if m.topic.endswith("/state")}


def test_twenty_supervisors_forty_units_one_broker(tmp_path: Path) -> None:
    robots = {n: [f"{n}-rover"] for n in [*names(), "victim"]}
    with running(tmp_path / "broker", robots) as broker, contextlib.ExitStack() as stack:
        runs = {}
        started = time.monotonic()
        for n in names():
            cfg = config(tmp_path, n, broker, allow_estop=True, keepalive_s=5)
            runs[n] = stack.enter_context(
                supervisor(cfg, "--priority", "normal", "--record", str(tmp_path / f"{n}-bus.log"))
            )
        victim_cfg = config(tmp_path, "victim", broker, keepalive_s=5)
        victim = stack.enter_context(supervisor(victim_cfg, "--priority", "normal"))
        watch = fresh(broker, "all")
        watch.subscribe("abh3/v1/+/status")
        watch.subscribe("abh3/v1/+/units/+/state")
        watch.subscribe("abh3/v1/+/events")

        def all_online(w: Watcher, since: int = 0) -> None:
            online = set()

            def seen(m: Received) -> bool:
                if m.topic.endswith("/status") and m.body["state"] == "online":
                    online.add(m.topic)
                return len(online) == N + 1

            w.wait_for(seen, 120, since=since)

        all_online(watch)
        up = time.monotonic() - started
        watch.wait_for(lambda m: len(states_seen(watch)) == 2 * (N + 1), 30)

        # a fleet client that comes now: every unit's retained state
        t0 = time.monotonic()
        late = fresh(broker, "late")
        late.subscribe("abh3/v1/+/units/+/state")
        late.wait_for(lambda m: len(states_seen(late)) == 2 * (N + 1), 2.0)
        seen_40 = time.monotonic() - t0

        # the broker restarts (no persistence: retained state is gone until republished)
        broker.stop()
        watch.close()
        late.close()
        broker.start()
        t0 = time.monotonic()
        again = fresh(broker, "again")
        again.subscribe("abh3/v1/+/status")
        again.subscribe("abh3/v1/+/units/+/state")
        all_online(again)
        reconnected = time.monotonic() - t0
        again.wait_for(lambda m: len(states_seen(again)) == 2 * (N + 1), 10)
        states_back = time.monotonic() - t0
        assert reconnected <= 10
        assert not again.invalid

        # one of them killed -9: connection broken within its keep-alive (5 s)
        os.kill(victim.proc.pid, signal.SIGKILL)
        killed = time.monotonic()
        again.wait_for(
            lambda m: (
                m.topic == "abh3/v1/victim-rover/status" and m.body["state"] == "connection_broken"
            ),
            15,
        )
        will = time.monotonic() - killed
        assert will <= 1.5 * 5 + 0.5

        # an e-stop to all
        again.subscribe("abh3/v1/+/events")
        sent = time.time()
        again.publish(
            Topics("all").command("estop", everyone=True),
            payloads.estop_command(1, sent, sender="scale", reason="scale test"),
        )
        latched: set[str] = set()

        def every_latch(m: Received) -> bool:
            if m.topic.endswith("/events") and m.body["kind"] == "estop_latched":
                latched.add(m.topic)
            return len(latched) == N  # the victim is dead: it latches nothing

        again.wait_for(every_latch, 30)
        again.close()
    latencies = []
    for n in names():
        assert runs[n].proc.returncode == 0, runs[n].log()
        first = stop_frames(tmp_path / f"{n}-bus.log", sent)
        assert set(first) == {1, 3}, (n, first)
        latencies += [t - sent for t in first.values()]
    latencies.sort()
    p50 = statistics.median(latencies)
    p99 = latencies[min(len(latencies) - 1, round(0.99 * (len(latencies) - 1)))]
    print(
        f"\nfleet scale: {N} supervisors x 2 units: all online {up:.1f} s after start; "
        f"a new client saw {2 * (N + 1)} unit states in {seen_40 * 1000:.0f} ms; broker restart: "
        f"all online again in {reconnected:.2f} s, all states in {states_back:.2f} s; "
        f"e-stop to all -> stop frame: p50 {p50 * 1000:.0f} ms, p99 {p99 * 1000:.0f} ms, "
        f"max {latencies[-1] * 1000:.0f} ms ({len(latencies)} units); a supervisor killed -9: "
        f"connection_broken after {will:.1f} s (keep-alive 5 s)"
    )
    assert seen_40 <= 2.0
    assert p99 <= 0.25
