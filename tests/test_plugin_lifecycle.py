"""Plugins cannot hold the drives hostage: start before motion, deadlines on every hook."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.errors import PluginError
from abh3_supervisor.plugin_host import host as plugin_host
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.stopping import CONFIRMED
from tests.support.rig import TWO_UNITS

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

CONFIG = parse_config(TWO_UNITS, "t.yaml")


class Good:
    def __init__(self) -> None:
        self.started = self.stopped = False

    @hookimpl
    def abh3_start(self) -> None:
        self.started = True

    @hookimpl
    def abh3_stop(self) -> None:
        self.stopped = True


class FailsToStart:
    @hookimpl
    def abh3_start(self) -> None:
        raise PermissionError(13, "Permission denied", "/proc/out.csv")


class Blocks:
    """Blocks in one hook until released (the test releases it: no thread outlives it)."""

    def __init__(self, hook: str) -> None:
        self.hook, self.release = hook, threading.Event()

    def _maybe_block(self, hook: str) -> None:
        if hook == self.hook:
            self.release.wait()

    @hookimpl
    def abh3_start(self) -> None:
        self._maybe_block("abh3_start")

    @hookimpl
    def abh3_stop(self) -> None:
        self._maybe_block("abh3_stop")


def host_with(*plugins: tuple[str, object]) -> PluginHost:
    host = PluginHost(CONFIG)
    for name, plugin in plugins:
        host.register(plugin, name)
    return host


def test_a_plugin_that_cannot_start_fails_the_run_before_any_frame() -> None:
    good = Good()
    host = host_with(("good", good), ("out", FailsToStart()))
    rt = Runtime(CONFIG, plugins=host)

    async def scenario() -> None:
        async with rt:
            pytest.fail("the run must not start")

    with pytest.raises(PluginError, match=r"plugin out could not start \(abh3_start\).*Perm"):
        asyncio.run(scenario())
    assert good.started and good.stopped  # what did start is closed again
    assert all(d.frames_received == 0 for d in rt.sims["b"].drives.values())  # nothing sent


def test_a_plugin_blocking_in_start_fails_the_run_at_its_deadline(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(plugin_host, "START_DEADLINE_S", 0.2)
    blocks = Blocks("abh3_start")
    rt = Runtime(CONFIG, plugins=host_with(("slow", blocks)))

    async def scenario() -> None:
        async with rt:
            pytest.fail("the run must not start")

    try:
        with pytest.raises(PluginError, match=r"did not return within 0\.2 s"):
            asyncio.run(scenario())
        assert all(d.frames_received == 0 for d in rt.sims["b"].drives.values())
    finally:
        blocks.release.set()


def test_a_plugin_blocking_in_stop_is_left_behind_with_the_drives_stopped(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    monkeypatch.setattr(plugin_host, "STOP_DEADLINE_S", 0.2)
    blocks = Blocks("abh3_stop")
    rt = Runtime(CONFIG, plugins=host_with(("stuck", blocks)), record=tmp_path / "r.log")

    async def scenario() -> None:
        async with rt:
            sup = rt.supervisor
            since = sup.clock()
            assert all(await asyncio.gather(*(sup.wait_exchange(n, since, 2) for n in sup.units)))

    start = time.monotonic()
    try:
        with caplog.at_level(logging.INFO):
            asyncio.run(scenario())
        assert time.monotonic() - start < 5
        assert rt.stop_report == {"left": CONFIRMED, "right": CONFIRMED}
        assert "plugin stuck failed in abh3_stop: did not return within 0.2 s" in caplog.text
        assert (tmp_path / "r.log").stat().st_size > 0  # closed after the stop frames
    finally:
        blocks.release.set()


class StuckSource(InputSource):
    """An input whose device will not let go."""

    def __init__(self) -> None:
        super().__init__("stuck", ("left",))
        self.release = threading.Event()
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.release.wait()


class ProvidesStuck:
    def __init__(self) -> None:
        self.source = StuckSource()

    @hookimpl
    def abh3_input_sources(self, register: Any) -> None:
        register(self.source)


def test_an_input_whose_stop_blocks_cannot_keep_the_drives_running(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(plugin_host, "STOP_DEADLINE_S", 0.2)
    plugin = ProvidesStuck()
    rt = Runtime(CONFIG, plugins=host_with(("stuck", plugin)))

    async def scenario() -> None:
        async with rt:
            sup = rt.supervisor
            for text in ("SERVO ON ON", "START ON ON"):
                assert await sup.command("left", text) == ""
            assert plugin.source.feed is not None
            plugin.source.feed.velocity(100.0, 0.0)
            await sup.wait_exchange("left", sup.clock(), 1)

    try:
        with caplog.at_level(logging.INFO):
            asyncio.run(scenario())
        assert rt.stop_report == {"left": CONFIRMED, "right": CONFIRMED}  # stopped first
        left = rt.sims["b"].drives[1]
        assert left.cmd_raw == (0, 0) and not left.inputs & left.layout.servo.both
        assert "input stuck failed to stop: did not return within 0.2 s" in caplog.text
    finally:
        plugin.source.release.set()


SLOW_PLUGIN = """
import sys, threading
from abh3_supervisor.plugin_host.hookspecs import hookimpl

class Slow:
    @hookimpl
    def abh3_configure(self, section):
        pass

    @hookimpl
    def abh3_start(self):
        print("slow: starting", file=sys.stderr, flush=True)
        threading.Event().wait()
"""
RUN_WITH_SLOW = """
import sys
from importlib.metadata import EntryPoint
import abh3_supervisor.plugin_host.host as host
host.installed = lambda: {"slow": EntryPoint("slow", "slowplugin:Slow", "abh3_supervisor")}
from abh3_supervisor.clients.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_while_a_plugin_blocks_starting_ends_the_run_at_once(
    tmp_path: Path, sig: signal.Signals
) -> None:
    (tmp_path / "slowplugin.py").write_text(SLOW_PLUGIN)
    (tmp_path / "run.py").write_text(RUN_WITH_SLOW)
    config = tmp_path / "c.yaml"
    config.write_text(
        TWO_UNITS.replace("channel: t", "channel: slowstart") + "plugins:\n  slow: {}\n"
    )
    proc = subprocess.Popen(
        [sys.executable, str(tmp_path / "run.py"), "run", str(config), "--headless",
         "--no-socket", "--record", str(tmp_path / "r.log")],
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"},
    )  # fmt: skip
    assert proc.stderr is not None
    for line in proc.stderr:
        if "slow: starting" in line:
            break
    sent = time.monotonic()
    proc.send_signal(sig)
    rest = proc.stderr.read()
    code = proc.wait(10)
    assert time.monotonic() - sent < 1.5, rest  # at once, not at the 5 s start deadline
    assert code == 128 + sig, rest
    assert f"stopped by {sig.name} while starting; no drive was started" in rest
    assert "Traceback" not in rest and "Exception ignored" not in rest
    assert b"EF0" not in (tmp_path / "r.log").read_bytes().upper()  # not one command frame
