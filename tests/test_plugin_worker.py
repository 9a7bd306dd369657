"""A plugin's worker (plugin_host/host.py ``_Worker``): events in order, none lost while
the queue has room, and the thread woken once for a batch rather than once per event —
for the bus loop's events, once per step of the loop, after it."""

from __future__ import annotations

import asyncio
import functools
import threading
import time
from collections.abc import Callable, Generator
from typing import Any, cast

import pluggy
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.journal import Journal
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
        journal = Journal()  # the supervisor's: each event written once
        host._reader = journal.reader()
        worker = host.workers["plain"] = host_module._Worker(host, "plain")
        sets = counted_wakes(worker)

        def emit(event: HealthEvent) -> None:  # as Supervisor._emit and _tell do
            journal.write(event)
            host._news()

        for i in range(5):  # one step of the loop: five events
            emit(HealthEvent("u", float(i), i % 2 == 0))
        assert not worker.held and not worker.items and sets == []  # none yet
        await asyncio.sleep(0)  # the step is over: the loop runs the release queued by it
        assert not worker.held and len(sets) == 1
        emit(HealthEvent("u", 5.0, False))  # the next step's
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


class VirtualTime:
    """``time.monotonic`` and ``time.sleep`` for a worker stepped by the test: a sleep
    is recorded and moves the clock on at once, doing on the way what was due (``at``:
    the loop's releases)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.now = 100.0
        self.rests: list[float] = []
        self.due: list[tuple[float, Callable[[], None]]] = []
        monkeypatch.setattr(time, "monotonic", lambda: self.now)  # the module host.py uses
        monkeypatch.setattr(time, "sleep", self.sleep)

    def at(self, when: float, action: Callable[[], None]) -> None:
        self.due = sorted([*self.due, (when, action)], key=lambda entry: entry[0])

    def sleep(self, rest: float) -> None:
        self.rests.append(rest)
        self.advance(rest)

    def advance(self, dt: float) -> None:
        end = self.now + dt
        while self.due and self.due[0][0] <= end:
            self.now, action = self.due.pop(0)
            action()
        self.now = end


class Woken:
    """A stepped worker's wake-up: a wait lets ``late`` pass on the virtual clock, in
    which a release must wake it (else the test fails: it would wait for ever)."""

    def __init__(self, t: VirtualTime) -> None:
        self.t, self.flag, self.late, self.waits = t, False, 0.0, 0

    def set(self) -> None:
        self.flag = True

    def clear(self) -> None:
        self.flag = False

    def wait(self, timeout: float | None = None) -> bool:
        self.waits += 1
        self.t.advance(self.late)
        assert self.flag, "the thread would wait to be woken"
        return True


def stepped_worker(t: VirtualTime) -> tuple[host_module._Worker, Woken]:
    """A worker whose thread is not started: the test calls its waits itself (its host
    is never called)."""
    worker = host_module._Worker(Host(), "p", start=False)  # type: ignore[arg-type]
    woken = Woken(t)
    worker._wake = woken  # type: ignore[assignment]
    return worker, woken


def batch(worker: host_module._Worker) -> None:
    """The worker's next batch begins (its wait), and takes what is queued."""
    worker._next_batch()
    worker.items.clear()


def release(worker: host_module._Worker) -> None:
    """A loop step's events, handed over."""
    worker.hold("abh3_tick", {"i": 0})
    worker.release()


def test_batches_start_at_least_a_spacing_apart(monkeypatch: pytest.MonkeyPatch) -> None:
    """A bus watched frame by frame releases events at every frame: the thread rests
    the remainder of ``SPACING_S`` before a batch that comes sooner after the last."""
    t = VirtualTime(monkeypatch)
    worker, _ = stepped_worker(t)
    release(worker)  # the first batch, at 100.0: at once
    batch(worker)
    assert worker.began == 100.0 and t.rests == []
    t.now += 0.001
    release(worker)  # 1 ms later: rests the remainder first
    batch(worker)
    assert t.rests == [pytest.approx(host_module.SPACING_S - 0.001)]
    t.now += 0.5
    release(worker)  # long after: at once
    batch(worker)
    assert len(t.rests) == 1 and worker.began == t.now


def paced(t: VirtualTime, worker: host_module._Worker, woken: Woken) -> float:
    """The loop releases a step's events every 10 ms from 100.0 on (a bus at 100 Hz);
    the first two batches, woken by it. When the second began."""
    period = host_module.SPACING_S
    for k in range(1, 10):
        t.at(100.0 + k * period, functools.partial(release, worker))
    release(worker)
    batch(worker)
    woken.late = period  # the thread waits for the next release, which wakes it
    batch(worker)
    assert woken.waits == 1 and worker.began == pytest.approx(100.0 + period)
    return worker.began


def test_while_batches_come_a_spacing_apart_the_thread_sleeps_to_the_next_release(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A bus at 100 Hz: the thread sleeps until just after the loop's next release is
    due and finds its events there; it never waits to be woken again."""
    t = VirtualTime(monkeypatch)
    worker, woken = stepped_worker(t)
    began, period = paced(t, worker, woken), host_module.SPACING_S
    for n in range(1, 6):
        batch(worker)
        assert worker.began == pytest.approx(began + n * period + host_module.LAG_S)
    assert woken.waits == 1  # never waited to be woken again


def test_a_release_that_is_late_is_waited_for_and_the_pace_taken_from_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A late step: nothing waits when the thread wakes, so it waits to be woken; once
    the releases come a spacing apart again it sleeps to them by itself."""
    t = VirtualTime(monkeypatch)
    worker, woken = stepped_worker(t)
    began, period = paced(t, worker, woken), host_module.SPACING_S
    late = 0.003
    t.due = [(when + late, action) for when, action in t.due]  # from now on 3 ms late
    woken.late = late - host_module.LAG_S  # the next release comes after the wake-up
    batch(worker)
    assert woken.waits == 2 and worker.began == pytest.approx(began + period + late)
    woken.late = period  # 13 ms since the last release: woken by the next one too
    batch(worker)
    assert woken.waits == 3 and worker.began == pytest.approx(began + 2 * period + late)
    batch(worker)  # a spacing apart again: by itself
    assert worker.began == pytest.approx(began + 3 * period + late + host_module.LAG_S)


def test_releases_further_apart_than_a_spacing_are_waited_for_without_a_wasted_wake_up(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A bus at 50 Hz: the thread sleeps to nothing it would not find, it is woken."""
    t = VirtualTime(monkeypatch)
    worker, woken = stepped_worker(t)
    for k in range(1, 6):
        t.at(100.0 + k * 0.020, functools.partial(release, worker))
    release(worker)
    batch(worker)
    woken.late = 0.0201  # each wait sees the next release
    for _ in range(5):
        batch(worker)
    assert woken.waits == 5 and t.rests == []
