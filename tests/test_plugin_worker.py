"""A plugin's worker (plugin_host/host.py ``_Worker``): events in order, none lost while
the queue has room, and the thread woken once for a batch rather than once per event."""

from __future__ import annotations

import threading
import time
from typing import Any

from abh3_supervisor.plugin_host import host as host_module


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
    sets: list[float] = []
    wake = worker._wake.set  # the event the thread waits on, counted

    def counted() -> None:
        sets.append(time.monotonic())
        wake()

    worker._wake.set = counted  # type: ignore[method-assign]
    worker.post("abh3_tick", {"i": 0})
    assert host.started.wait(10)  # the first event woke it; its hook holds it
    woken = len(sets)
    for i in range(1, 200):
        worker.post("abh3_tick", {"i": i})
    assert len(sets) == woken  # busy: the 199 gather without waking anything
    host.release.set()
    worker.close(time.monotonic() + 10)
    assert host.calls == list(range(200)) and not worker.thread.is_alive()


def test_a_full_queue_drops_and_counts_never_waits() -> None:
    host = Host()
    worker = host_module._Worker(host, "p")  # type: ignore[arg-type]
    worker.post("abh3_tick", {"i": 0})
    assert host.started.wait(10)
    for i in range(1, host_module.QUEUE_SIZE + 51):
        worker.post("abh3_tick", {"i": i})
    assert worker.dropped == 50 and not worker.ask_to_end()  # full: the marker waits too
    host.release.set()
    worker.close(time.monotonic() + 10)
    assert host.calls == list(range(host_module.QUEUE_SIZE + 1))
