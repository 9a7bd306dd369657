"""A plugin's worker (plugin_host/host.py ``_Worker``): events in order, none lost while
the queue has room, and the thread woken once for a batch rather than once per event —
for the bus loop's events, once per step of the loop, after it."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Generator
from typing import Any, cast

import pluggy
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.plugin_host import host as host_module
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.scheduler.core import HealthEvent


class Host:
    """What a worker uses of its host: a hook that holds the first call until released."""

    below_loop: frozenset[str] = frozenset()

    def __init__(self) -> None:
        self.calls: list[int] = []
        self.started = threading.Event()
        self.release = threading.Event()

    def thread_setup(self, below_loop: bool) -> None:
        pass

    def call_one(self, name: str, hook: str, **kwargs: Any) -> None:
        if not self.calls:
            self.started.set()
            self.release.wait(10)
        self.calls.append(kwargs["i"])


def test_events_posted_while_the_worker_is_busy_wake_it_once_and_all_arrive_in_order() -> None:
    host = Host()
    worker = host_module._Worker(host, "p")  # type: ignore[arg-type]
    sets = counted_wakes(worker)
    worker.post("abh3_tick", {"i": 0})
    assert host.started.wait(10)  # the first event woke it; its hook holds it
    woken = len(sets)
    for i in range(1, 200):
        worker.post("abh3_tick", {"i": i})
    assert len(sets) == woken  # busy: the 199 gather without waking anything
    host.release.set()
    worker.close(time.monotonic() + 10)
    assert host.calls == list(range(200)) and not worker.thread.is_alive()


def counted_wakes(worker: host_module._Worker) -> list[float]:
    """Each time the thread is woken (its event set), from now on."""
    sets: list[float] = []
    wake = worker._wake.set

    def counted() -> None:
        sets.append(time.monotonic())
        wake()

    worker._wake.set = counted  # type: ignore[method-assign]
    return sets


def test_the_events_of_one_loop_step_reach_the_worker_after_it_in_one_wake_up() -> None:
    plain = Plain()
    host = plugin_host(plain=plain)

    async def run() -> None:
        host._sup, host._loop = cast(Any, object()), asyncio.get_running_loop()
        worker = host.workers["plain"] = host_module._Worker(host, "plain")
        sets = counted_wakes(worker)
        for i in range(5):  # one step of the loop: five events
            host._observe(HealthEvent("u", float(i), i % 2 == 0))
        assert len(worker.held) == 5 and not worker.items and sets == []  # none yet
        await asyncio.sleep(0)  # the step is over: the loop runs the release queued by it
        assert not worker.held and len(sets) == 1
        host._observe(HealthEvent("u", 5.0, False))  # the next step's
        await asyncio.sleep(0)
        worker.close(time.monotonic() + 10)
        assert not worker.thread.is_alive()

    asyncio.run(run())
    assert plain.seen == [("u", i % 2 == 0) for i in range(5)] + [("u", False)]


def test_what_the_loop_held_goes_before_the_end_marker() -> None:
    host = Host()
    host.release.set()
    worker = host_module._Worker(host, "p")  # type: ignore[arg-type]
    for i in range(3):
        worker.hold("abh3_tick", {"i": i})
    worker.close(time.monotonic() + 10)  # the run ended before the loop released them
    assert host.calls == [0, 1, 2] and not worker.thread.is_alive()


def test_a_full_queue_drops_and_counts_never_waits() -> None:
    host = Host()
    worker = host_module._Worker(host, "p")  # type: ignore[arg-type]
    worker.post("abh3_tick", {"i": 0})
    assert host.started.wait(10)
    for i in range(1, host_module.QUEUE_SIZE + 51):
        worker.post("abh3_tick", {"i": i})
    worker.hold("abh3_tick", {"i": -1})  # the loop's events count against the same bound
    assert worker.dropped == 51 and not worker.held
    assert not worker.ask_to_end()  # full: the marker waits too
    host.release.set()
    worker.close(time.monotonic() + 10)
    assert host.calls == list(range(host_module.QUEUE_SIZE + 1))


class Plain:
    """A plugin whose hook names only some of the hook's arguments."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, bool]] = []

    @hookimpl
    def abh3_health(self, unit: str, online: bool) -> None:
        self.seen.append((unit, online))


class Wrapping:
    """A plugin whose hook is a new-style wrapper: only pluggy knows how to run it."""

    def __init__(self) -> None:
        self.seen: list[str] = []

    @hookimpl(wrapper=True)
    def abh3_health(self, unit: str) -> Generator[None, None, None]:
        self.seen.append(unit)
        return (yield)


def plugin_host(**plugins: object) -> PluginHost:
    host = PluginHost(parse_config("buses: {b: {}}\nunits: [{name: u}]\n", "c.yaml"), available={})
    for name, plugin in plugins.items():
        host.register(plugin, name)
        host._caller(name, "abh3_health")  # as start() builds them, before any worker runs
    return host


def test_a_plain_hook_is_called_directly_with_the_arguments_it_names() -> None:
    plain, wrapping = Plain(), Wrapping()
    host = plugin_host(plain=plain, wrapping=wrapping)
    assert host._ignoring["plain", "abh3_health"] is not host._callers["plain", "abh3_health"]
    assert host._ignoring["wrapping", "abh3_health"] is host._callers["wrapping", "abh3_health"]
    host.call_one("plain", "abh3_health", unit="u", online=True, t=1.0)
    host.call_one("wrapping", "abh3_health", unit="u", online=False, t=2.0)
    assert plain.seen == [("u", True)] and wrapping.seen == ["u"]


def test_a_direct_call_missing_an_argument_fails_as_pluggy_s_would() -> None:
    plain = Plain()
    host = plugin_host(plain=plain)
    host.call_one("plain", "abh3_health", unit="u", t=1.0)  # no `online`
    assert plain.seen == [] and host.failures == {"plain": 1}
    with pytest.raises(pluggy.HookCallError, match="'online'"):
        host._ignoring["plain", "abh3_health"](unit="u", t=1.0)


class Counting:
    """What a worker uses of its host: counts its calls, and lets a test wait for them."""

    below_loop: frozenset[str] = frozenset()

    def __init__(self) -> None:
        self.calls: list[int] = []
        self.changed = threading.Condition()

    def thread_setup(self, below_loop: bool) -> None:
        pass

    def call_one(self, name: str, hook: str, **kwargs: Any) -> None:
        with self.changed:
            self.calls.append(kwargs["i"])
            self.changed.notify_all()

    def wait_for(self, n: int) -> None:
        with self.changed:
            assert self.changed.wait_for(lambda: len(self.calls) >= n, timeout=10)


def test_batches_start_at_least_a_spacing_apart(monkeypatch: pytest.MonkeyPatch) -> None:
    """A bus watched frame by frame releases events at every frame: the thread rests
    the remainder of ``SPACING_S`` before a batch that comes sooner after the last."""
    clock = [100.0]
    rests: list[float] = []
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])  # the module host.py uses
    monkeypatch.setattr(time, "sleep", rests.append)  # the rest, not slept
    host = Counting()
    worker = host_module._Worker(host, "p")  # type: ignore[arg-type]
    worker.post("abh3_tick", {"i": 0})  # the first batch, at 100.0
    host.wait_for(1)
    clock[0] += 0.001
    worker.post("abh3_tick", {"i": 1})  # 1 ms later: rests 3 ms first
    host.wait_for(2)
    clock[0] += 0.010
    worker.post("abh3_tick", {"i": 2})  # long after: at once
    host.wait_for(3)
    assert host.calls == [0, 1, 2] and rests == [pytest.approx(0.003)]
    worker.close(clock[0] + 10)
