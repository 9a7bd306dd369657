"""The runtime on a thread and event loop of its own, for front ends with heavy work.

A UI that renders on its own loop must never delay the buses: here the schedulers run on
a dedicated loop; the UI reads supervisor state (attribute reads are atomic under the
GIL; containers the bus side mutates are copied in one C call first — ``list(deque)``,
``dict(d)`` — never iterated live) and hands every command over with :meth:`call` /
:meth:`run`. Stopping the
thread leaves the runtime, so the drives are stopped as on every other way out.
"""

from __future__ import annotations

import asyncio
import sys
import threading
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, TypeVar

from abh3_supervisor.config.model import Config
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.bus_runtime import Runtime

T = TypeVar("T")
# Python hands the GIL over every 5 ms by default; the bus thread waking on its timer
# must not wait that long behind the UI thread.
SWITCH_INTERVAL_S = 0.0005


class RuntimeThread:
    def __init__(self, config: Config, *, record: Path | None, plugins: PluginHost | None) -> None:
        self.config, self.record, self.plugins = config, record, plugins
        self.runtime: Runtime | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self.error: BaseException | None = None
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._main, name="abh3 runtime", daemon=True)
        self._switch = sys.getswitchinterval()

    def start(self) -> Runtime:
        """Start and wait until the buses run; re-raises what stopped them from starting."""
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        self._thread.start()
        self._ready.wait()
        if self.error is not None:
            self._thread.join()
            raise self.error
        assert self.runtime is not None
        return self.runtime

    def _main(self) -> None:
        asyncio.run(self._amain())

    async def _amain(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        try:
            async with Runtime(self.config, record=self.record, plugins=self.plugins) as rt:
                self.runtime = rt
                self._ready.set()
                await rt.run_until(self._stop)
        except BaseException as exc:  # handed to the starting thread, or kept for stop()
            self.error = exc
        finally:
            self._ready.set()

    def call(self, fn: Callable[..., object], *args: object) -> None:
        """Run ``fn(*args)`` on the runtime's loop, soon (from any thread)."""
        assert self.loop is not None
        self.loop.call_soon_threadsafe(fn, *args)

    async def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Await a coroutine run on the runtime's loop, from another loop."""
        assert self.loop is not None
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    @property
    def alive(self) -> bool:
        return self._thread.is_alive() and self.error is None

    def stop(self) -> None:
        """Leave the runtime (drives stopped and confirmed), then end the thread."""
        if self.loop is not None and self._stop is not None and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self._stop.set)
        self._thread.join()
        sys.setswitchinterval(self._switch)
