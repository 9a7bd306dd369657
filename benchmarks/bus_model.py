"""1. Bus utilisation and 5. planner accuracy, on a simulated wire (exact bit times).

Both strategies run on :class:`Timeline` with wire time and arbitration modelled, against
the same simulated drives answering after ``latency`` seconds:

* **ours** — one :class:`BusScheduler` for the bus, rates above capacity;
* **seed-style** — one node per drive with its own bus handle, doing one synchronous
  exchange at a time (send, block until the reply or the timeout, ``turnaround`` of host
  time, send again), as the vendor's ros2ABH3Cmd does per message.

The physical limit for N drives is the smaller of the wire's capacity and what the
protocol allows: one DP0 exchange in flight per drive (replies carry no sequence number),
so each drive can at best complete one exchange per (command time + latency + reply time).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

from abh3_supervisor.config.model import BroadcastConfig, Config, SimConfig, UnitConfig
from abh3_supervisor.core.planner import plan
from abh3_supervisor.core.wire import exact_bits
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.scheduler.core import BusScheduler
from abh3_supervisor.simulator import SimBus
from abh3_supervisor.simulator.timeline import Timeline

WARMUP, WINDOW = 0.1, 0.5


class SeedNode:
    """A vendor-style command node: its own handle, one blocking exchange at a time."""

    def __init__(
        self, abh3_id: int, host_id: int, timeout: float, turnaround: float, rate: float = 0.0
    ) -> None:
        # rate > 0: fed by a topic at that rate (one message, one blocking exchange)
        self.period, self.next_message = (1 / rate if rate else 0.0), 0.0
        self.cmd_id = ids.dp0_command_id(abh3_id, host_id)
        self.reply_id = ids.dp0_reply_id(abh3_id, host_id)
        self.payload = frames.encode_dp0_command(0, 0, 0)  # the same frame ours sends
        self.timeout, self.turnaround = timeout, turnaround
        self.waiting_since: float | None = None
        self.ready_at = 0.0
        self.done: list[float] = []

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        # the socket sees every frame on the bus; only its own reply ends the wait
        if self.waiting_since is not None and arbitration_id == self.reply_id:
            self.waiting_since = None
            self.ready_at = now + self.turnaround
            self.done.append(now)

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        if self.waiting_since is not None and now >= self.waiting_since + self.timeout:
            self.waiting_since = None  # timed out: the seed resets its socket and goes on
        if self.waiting_since is None and now >= max(self.ready_at, self.next_message):
            self.waiting_since = now
            self.next_message = max(self.next_message + self.period, now)
            return [(self.cmd_id, self.payload)]
        return []

    def next_deadline(self) -> float:
        if self.waiting_since is not None:
            return self.waiting_since + self.timeout
        return max(self.ready_at, self.next_message)

    def on_send_failed(self, arbitration_id: int) -> None:
        self.waiting_since = None

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        pass


class SeedPoller:
    """The seed's status node driven flat out: one broadcast request at a time, each
    waiting for its packet (or the timeout) — a second handle competing for the wire."""

    def __init__(self, unit: UnitConfig, timeout: float) -> None:
        self.request_id = ids.request_id(unit.abh3_id, unit.host_id)
        self.packets = [
            (ids.broadcast_id(unit.abh3_id, unit.brd_group, n),
             frames.encode_request(frames.broadcast_pgn(unit.brd_group, n)))
            for n in range(7)
        ]  # fmt: skip
        self.timeout, self.index = timeout, 0
        self.waiting_since: float | None = None

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        if self.waiting_since is not None and arbitration_id == self.packets[self.index][0]:
            self.waiting_since = None
            self.index = (self.index + 1) % len(self.packets)

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        if self.waiting_since is not None and now >= self.waiting_since + self.timeout:
            self.waiting_since = None
        if self.waiting_since is None:
            self.waiting_since = now
            return [(self.request_id, self.packets[self.index][1])]
        return []

    def next_deadline(self) -> float:
        return math.inf if self.waiting_since is None else self.waiting_since + self.timeout

    def on_send_failed(self, arbitration_id: int) -> None:
        self.waiting_since = None

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        pass


def _command_quality(
    timeline: Timeline, units: list[UnitConfig], rate: float, start: float, end: float
) -> tuple[float, float]:
    """(worst unit's completed exchanges per second / ``rate``, worst command age p99 [s]):
    the age is how long a drive went without a command frame, sampled on every gap."""
    worst_rate, worst_age = math.inf, 0.0
    for u in units:
        cmd, reply = (
            ids.dp0_command_id(u.abh3_id, u.host_id),
            ids.dp0_reply_id(u.abh3_id, u.host_id),
        )
        sent = [f.end for f in timeline.frames if f.arbitration_id == cmd and start <= f.end < end]
        done = [
            f.end for f in timeline.frames if f.arbitration_id == reply and start <= f.end < end
        ]
        worst_rate = min(worst_rate, len(done) / (end - start) / rate)
        gaps = sorted(b - a for a, b in itertools.pairwise(sent)) or [math.inf]
        worst_age = max(worst_age, gaps[min(len(gaps) - 1, int(0.99 * len(gaps)))])
    return worst_rate, worst_age


def polling_overload(
    n: int, bitrate: int, latency: float, rate: float = 100.0
) -> dict[str, tuple[float, float]]:
    """Status polling offered above the bus's capacity next to commands at ``rate``: what
    each strategy leaves of every unit's command exchange (rate fraction, age p99)."""
    units = [
        replace(u, broadcast=BroadcastConfig(mask=0x7F, rate_hz=100_000.0)) for u in _units(n, rate)
    ]
    end = WARMUP + 4 * WINDOW
    ours_line = Timeline(bitrate)
    ours_line.add(BusScheduler(units, 0.0))
    ours_line.add(_sim(units, latency))
    ours_line.run_until(end)
    seed_line = Timeline(bitrate)
    for u in units:
        seed_line.add(SeedNode(u.abh3_id, u.host_id, 0.1, 0.0, rate=rate))
        seed_line.add(SeedPoller(u, timeout=0.1))
    seed_line.add(_sim(units, latency))
    seed_line.run_until(end)
    return {
        "ours": _command_quality(ours_line, units, rate, WARMUP, end),
        "seed": _command_quality(seed_line, units, rate, WARMUP, end),
    }


def _units(n: int, rate: float) -> list[UnitConfig]:
    return [
        UnitConfig(
            name=f"u{i}",
            bus="b",
            abh3_id=i + 1,
            command_rate_hz=rate,
            broadcast=BroadcastConfig(mask=0),
        )
        for i in range(n)
    ]


def _sim(units: list[UnitConfig], latency: float) -> SimBus:
    return SimBus.for_units(
        units,
        SimConfig(reply_latency_ms=latency * 1000, command_zero_timeout_ms=0, error_timeout_ms=0),
        0.0,
    )


def _count(times: list[float]) -> float:
    return sum(1 for t in times if WARMUP <= t < WARMUP + WINDOW) / WINDOW


def ours(n: int, bitrate: int, latency: float) -> tuple[float, float]:
    """(exchanges/s, mean bits per exchange) for our scheduler with N units overloaded."""
    units = _units(n, rate=100_000.0)  # far above any share of the bus: offered > capacity
    timeline = Timeline(bitrate)
    scheduler = BusScheduler(units, 0.0)
    timeline.add(scheduler)
    timeline.add(_sim(units, latency))
    replies: list[float] = []
    reply_ids = {ids.dp0_reply_id(u.abh3_id, u.host_id) for u in units}
    timeline.run_until(WARMUP + WINDOW)
    replies = [f.end for f in timeline.frames if f.arbitration_id in reply_ids]
    bits = sum(exact_bits(f.arbitration_id, f.data) for f in timeline.frames) / max(1, len(replies))
    return _count(replies), bits


def seed_style(n: int, bitrate: int, latency: float, turnaround: float) -> float:
    units = _units(n, rate=1.0)
    timeline = Timeline(bitrate)
    nodes = [SeedNode(u.abh3_id, u.host_id, 1.0, turnaround) for u in units]
    for node in nodes:
        timeline.add(node)
    timeline.add(_sim(units, latency))
    timeline.run_until(WARMUP + WINDOW)
    return sum(_count(node.done) for node in nodes)


def physical_limit(n: int, bitrate: int, latency: float, bits_per_exchange: float) -> float:
    half = bits_per_exchange / 2 / bitrate
    return min(bitrate / bits_per_exchange, n / (2 * half + latency))


def planner_accuracy(bitrate: int = 500_000) -> tuple[float, float]:
    """(planned expected load %, load % measured on the wire) for a realistic 8-unit plan."""
    units = [
        replace(u, command_rate_hz=100.0, broadcast=BroadcastConfig(mask=0x7F, rate_hz=20.0))
        for u in _units(8, 1.0)
    ]
    config = Config(file="bench", buses={}, units={u.name: u for u in units})
    from abh3_supervisor.config.model import BusConfig

    config.buses["b"] = BusConfig(name="b", bitrate=bitrate)
    planned = plan(config)[0].load_percent
    timeline = Timeline(bitrate)
    scheduler = BusScheduler(units, 0.0)
    timeline.add(scheduler)
    timeline.add(_sim(units, 0.0005))
    timeline.run_until(2.0)
    measured = 100 * timeline.busy_time / 2.0
    return planned, measured


def utilisation_table(
    counts: list[int], bitrates: list[int], latency: float, seed_turnaround: float
) -> list[dict[str, float]]:
    rows = []
    for bitrate in bitrates:
        for n in counts:
            got, bits = ours(n, bitrate, latency)
            limit = physical_limit(n, bitrate, latency, bits)
            seed = seed_style(n, bitrate, latency, seed_turnaround)
            rows.append(
                {
                    "units": n,
                    "bitrate": bitrate,
                    "ours": got,
                    "seed": seed,
                    "limit": limit,
                    "wire_limit": bitrate / bits,
                    "percent": 100 * got / limit if limit else math.nan,
                }
            )
    return rows
