"""``abh3_tick``: a plugin's periodic call, at its section's ``tick_hz``.

One timer thread per plugin that implements the hook posts ``abh3_tick(t)`` to the
plugin's worker, so the tick runs on the same thread as its other observation hooks, one
at a time with them (no locks needed between them); queued when it falls due, it may run
before the events of a bus-loop step still in progress (host.py, ``_Worker``). The timer
keeps a fixed grid (a late tick does not shift the next); it sleeps on an event, so
closing it is immediate.
``tick_hz`` is the host's key, valid in every section, like ``on_error``: the plugin
never sees it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from abh3_supervisor.config.source import Section

HOOK = "abh3_tick"
KEY = "tick_hz"
DEFAULT_HZ = 10.0
MAX_HZ = 100.0  # a tick is a queued call on the plugin's worker, not a control loop


def take_rate(section: Section) -> tuple[float, dict[str, Any]]:
    """``tick_hz`` from a plugin's section (checked there, file:line on a problem) and
    the section without it, for the plugin."""
    raw = section.data
    if not isinstance(raw, dict) or KEY not in raw:
        return DEFAULT_HZ, raw
    hz = section.number(KEY, DEFAULT_HZ, 0.0, MAX_HZ, lo_open=True)
    return hz, {k: v for k, v in raw.items() if k != KEY}


class Ticker:
    """Calls ``post(HOOK, {"t": clock()})`` every ``1 / hz`` seconds until closed."""

    def __init__(
        self,
        name: str,
        hz: float,
        clock: Callable[[], float],
        post: Callable[[str, dict[str, Any]], None],
        setup: Callable[[], None] = lambda: None,
    ) -> None:
        self.period = 1.0 / hz
        self._clock, self._post, self._setup = clock, post, setup
        self._closed = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"plugin {name} tick", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        self._setup()  # normal priority, as every thread plugin code runs on
        due = time.monotonic() + self.period
        while not self._closed.wait(max(0.0, due - time.monotonic())):
            self._post(HOOK, {"t": self._clock()})
            due += self.period
            now = time.monotonic()
            if due < now:  # fell behind (a suspended process): skip, never burst
                due = now + self.period

    def close(self) -> None:
        self._closed.set()
        self.thread.join(1.0)
