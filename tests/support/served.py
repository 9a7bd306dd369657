"""Supervisors served in-process: a runtime on simulated drives with its control sockets,
on a thread of its own (:class:`Served`, and the ``served`` fixture conftest.py offers) or
on the test's loop (:func:`served`)."""

from __future__ import annotations

import asyncio
import select
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.server import ControlServer
from abh3_supervisor.service.view_pace import of_runtime
from tests.support.rig import TWO_UNITS


class Served:
    """A runtime on simulated drives with a control socket (and a read-only one), on a
    thread of its own, so tests talk to it with blocking clients as a script would."""

    def __init__(self, tmp: Path, config: str = TWO_UNITS) -> None:
        self.path, self.ro_path = tmp / "ctl" / "t.sock", tmp / "ctl" / "t-ro.sock"
        self.config = parse_config(config, "t.yaml")
        self.ready = threading.Event()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.stop: asyncio.Event | None = None
        self.rt: Runtime | None = None
        self.thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)

    async def _main(self) -> None:
        self.loop, self.stop = asyncio.get_running_loop(), asyncio.Event()
        host = PluginHost(self.config)
        async with Runtime(self.config, plugins=host) as rt:
            self.rt = rt
            pace = self.pace = of_runtime(rt)  # shared, as `abh3 run` shares it (headless.py)
            servers = [
                ControlServer(rt, host, self.path, pace=pace),
                ControlServer(rt, host, self.ro_path, read_only=True, pace=pace),
            ]
            for server in servers:
                await server.start()
            self.servers = servers
            self.ready.set()
            await self.stop.wait()
            for server in servers:
                await server.close()

    def on_loop(self, fn: Any, *args: Any) -> Any:
        """Run fn on the runtime's loop and return its result (state is the loop's)."""
        assert self.loop is not None

        async def run() -> Any:
            return fn(*args)

        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(5)

    def __enter__(self) -> Served:
        self.thread.start()
        assert self.ready.wait(10)
        return self

    def __exit__(self, *exc: object) -> None:
        assert self.loop is not None and self.stop is not None
        self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(10)


@pytest.fixture(name="served")
def served_thread(tmp_path: Path) -> Iterator[Served]:
    """The ``served`` fixture: :class:`Served` on TWO_UNITS for the test's length."""
    with Served(tmp_path) as s:
        yield s


def served(check: Callable[[Runtime, ControlServer, Path], Any], config: str = TWO_UNITS) -> None:
    """A runtime on simulated drives serving a socket; ``check`` attaches what it likes."""
    cfg = parse_config(config, "t.yaml")
    host = PluginHost(cfg)

    async def scenario(path: Path) -> None:
        async with Runtime(cfg, plugins=host) as rt:
            sup = rt.supervisor
            since = sup.clock()
            assert all(await asyncio.gather(*(sup.wait_exchange(n, since, 2) for n in sup.units)))
            server = ControlServer(rt, host, path)
            await server.start()
            try:
                await check(rt, server, path)
            finally:
                await server.close()

    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        asyncio.run(scenario(Path(tmp) / "s" / "t.sock"))


def wait_for(condition: Callable[[], bool], what: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"never happened: {what}"
        select.select([], [], [], 0.05)  # polling another process: nothing to wait on


async def no_clients(server: ControlServer) -> None:
    """Until the server has let every client go (its side runs on this loop), bounded."""
    for _ in range(400):
        if not server.clients:
            return
        await asyncio.sleep(0.005)
    raise AssertionError(f"clients still connected: {[c.name for c in server.clients]}")
