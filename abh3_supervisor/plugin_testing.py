"""Test a plugin on the simulator: the supported harness for plugin authors.

``run_with_plugin(config, plugin, name, seconds)`` runs a configuration exactly as
``abh3 run --headless`` does (the same plugin loading, checks, threads, stop path and exit
code), with every bus on the built-in simulator (python-can's in-process ``virtual`` bus,
on a channel of its own) and ``plugin`` — an object built by the test — loaded as if
installed under ``name``. It returns what the run produced: the records every plugin
received, the notices, the frames on the wire and the exit code. :func:`running` is the
same as a context manager that yields while the run goes on (wait for a condition with
:meth:`PluginRun.wait_for`, never sleep); ``abh3_run`` is the same as a pytest fixture.

The run takes ``seconds`` of real time: the supervisor's timing is the subject, and the
plugin's threads are real threads. A second or two is enough for most tests.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any, cast

import can

from abh3_supervisor.config import load_config, parse_config
from abh3_supervisor.config.model import Config, SimConfig
from abh3_supervisor.core.state import Feedback, Setpoint
from abh3_supervisor.core.supervisor import FlagChange, Notice
from abh3_supervisor.errors import Abh3Error, ConfigError, RunError
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import PluginHost, installed
from abh3_supervisor.protocol.frames import Broadcast
from abh3_supervisor.runtime.headless import run_headless

RECORDER = "abh3-plugin-testing"  # the harness's own plugin, beside the one under test
_runs = itertools.count(1)


@dataclass(frozen=True)
class Frame:
    """One frame on a bus, from either side."""

    t: float  # seconds since the run began
    bus: str
    arbitration_id: int
    data: bytes


@dataclass
class PluginRun:
    """What one run produced; the lists fill while it goes on (:func:`running`)."""

    feedback: list[tuple[str, Feedback, Setpoint]] = field(default_factory=list)
    status: list[tuple[str, int, Broadcast, float]] = field(default_factory=list)
    health: list[tuple[str, bool, float]] = field(default_factory=list)
    flags: list[FlagChange] = field(default_factory=list)
    notices: list[Notice] = field(default_factory=list)
    frames: list[Frame] = field(default_factory=list)
    log: list[str] = field(default_factory=list)  # the run's log lines, INFO and above
    exit_code: int | None = None  # None while it runs; as `abh3 run` would exit
    error: str | None = None  # why it ended before it began (bad settings, failed start)
    sources: list[str] = field(default_factory=list)  # the input sources that took part
    disabled: list[str] = field(default_factory=list)  # plugins switched off on failures
    _changed: threading.Condition = field(default_factory=threading.Condition, repr=False)

    def add(self, items: list[Any], item: Any) -> None:
        with self._changed:
            items.append(item)
            self._changed.notify_all()

    def wait_for(self, condition: Callable[[PluginRun], bool], timeout: float = 10.0) -> bool:
        """Wait until ``condition(self)`` holds (checked on every new record) or the run
        ends; whether it holds."""
        end = time.monotonic() + timeout
        with self._changed:
            while not condition(self) and self.exit_code is None:
                left = end - time.monotonic()
                if left <= 0:
                    break
                self._changed.wait(left)
            return condition(self)

    def frames_of(self, arbitration_id: int, mask: int = 0x1FFFFFFF) -> list[Frame]:
        """The frames whose id, under ``mask``, is ``arbitration_id``."""
        return [f for f in list(self.frames) if f.arbitration_id & mask == arbitration_id]

    def _end(self, code: int, error: str | None = None) -> None:
        with self._changed:
            self.exit_code, self.error = code, error
            self._changed.notify_all()


class _Recorder:
    """Registered beside the plugin under test: every observation record, as delivered."""

    def __init__(self, run: PluginRun) -> None:
        self.run = run

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback, setpoint: Setpoint) -> None:
        self.run.add(self.run.feedback, (unit, feedback, setpoint))

    @hookimpl
    def abh3_status(self, unit: str, packet: int, record: Broadcast, t: float) -> None:
        self.run.add(self.run.status, (unit, packet, record, t))

    @hookimpl
    def abh3_health(self, unit: str, online: bool, t: float) -> None:
        self.run.add(self.run.health, (unit, online, t))

    @hookimpl
    def abh3_flags(self, change: FlagChange) -> None:
        self.run.add(self.run.flags, change)

    @hookimpl
    def abh3_notice(self, notice: Notice) -> None:
        self.run.add(self.run.notices, notice)


class _Given:
    """An entry point that loads the object the test built (as an installed one would)."""

    def __init__(self, plugin: object) -> None:
        self.plugin = plugin

    def load(self) -> object:
        return self.plugin


def simulated(config: Config, settings: dict[str, Any] | None, name: str) -> Config:
    """Every bus on the simulator, on a virtual channel no other run uses; the plugin's
    section (``settings``) added when the file has none."""
    n = next(_runs)
    buses = {
        b: dataclasses.replace(
            cfg,
            interface="virtual",
            channel=f"abh3-plugin-test-{n}-{b}",
            options={},
            simulate=cfg.simulate or SimConfig(),
        )
        for b, cfg in config.buses.items()
    }
    plugins = dict(config.plugins)
    if name not in plugins:
        plugins[name] = dict(settings or {})
    return dataclasses.replace(config, buses=buses, plugins=plugins)


def _config(config: str | Path) -> Config:
    """A path (a Path, or a str naming an existing .yaml file) or YAML text."""
    if isinstance(config, Path):
        return load_config(config)
    if "\n" not in config and config.endswith((".yaml", ".yml")):
        return load_config(config)
    return parse_config(config, "<test config>")


class _Wire:
    """Every frame on each simulated bus, seen as another node would see it."""

    def __init__(self, config: Config, run: PluginRun, start: float) -> None:
        self.run, self.start = run, start
        self.done = threading.Event()
        self.buses = {
            name: can.Bus(interface="virtual", channel=cfg.channel)
            for name, cfg in config.buses.items()
        }
        self.thread = threading.Thread(target=self._read, name="plugin test wire", daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self.done.is_set():
            for name, bus in self.buses.items():
                while (msg := bus.recv(0.01)) is not None:
                    frame = Frame(
                        msg.timestamp - self.start, name, msg.arbitration_id, bytes(msg.data)
                    )
                    self.run.add(self.run.frames, frame)

    def close(self) -> None:
        self.done.set()
        self.thread.join(5)
        for bus in self.buses.values():
            bus.shutdown()


class _Lines(logging.Handler):
    def __init__(self, run: PluginRun) -> None:
        super().__init__(logging.INFO)
        self.run = run
        self.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        self.run.add(self.run.log, self.format(record))


@contextlib.contextmanager
def _logging(run: PluginRun) -> Iterator[None]:
    """Every log line of the run into ``run.log``, the plugin's own too (INFO and up while
    it runs: the root logger's level is lowered to INFO meanwhile, if it was higher)."""
    handler = _Lines(run)
    root = logging.getLogger()
    level = root.level
    root.addHandler(handler)
    if root.level > logging.INFO:
        root.setLevel(logging.INFO)
    try:
        yield
    finally:
        root.removeHandler(handler)
        root.setLevel(level)


@contextlib.contextmanager
def running(
    config: str | Path,
    plugin: object,
    name: str = "plugin",
    seconds: float = 1.0,
    settings: dict[str, Any] | None = None,
) -> Iterator[PluginRun]:
    """Run ``config`` for ``seconds`` with ``plugin`` loaded as ``name`` (its section:
    the file's ``plugins.<name>``, else ``settings``); yields while it runs, returns once
    it has ended with everything stopped. Other plugins the file names load as usual."""
    run = PluginRun()
    try:
        cfg = simulated(_config(config), settings, name)
    except ConfigError as exc:  # as `abh3 run` would: exit 2, the problems said
        run._end(2, "\n".join(exc.problems))
        yield run
        return
    available = {**installed(), name: cast(EntryPoint, _Given(plugin))}
    failure: list[BaseException] = []

    def main() -> None:
        host: PluginHost | None = None
        try:
            host = PluginHost(cfg, available)
            host.register(_Recorder(run), RECORDER)
            code = asyncio.run(
                run_headless(cfg, duration=seconds, record=None, status_interval=0, plugins=host)
            )
        except ConfigError as exc:
            run._end(2, "\n".join(exc.problems))
        except RunError as exc:
            run._end(1, str(exc))
        except Abh3Error as exc:
            run._end(2, str(exc))
        except BaseException as exc:  # the harness's own trouble: raised in the test
            failure.append(exc)
            run._end(1, repr(exc))
        else:
            run._end(code)
        finally:
            if host is not None:
                run.sources = [s.name for s in host.sources]
                run.disabled = sorted(host.disabled)

    with _logging(run):
        wire = _Wire(cfg, run, time.time())
        thread = threading.Thread(target=main, name=f"plugin test {name}")
        try:
            thread.start()
            yield run
        finally:
            thread.join()
            wire.close()
    if failure:
        raise failure[0]


def run_with_plugin(
    config: str | Path,
    plugin: object,
    name: str = "plugin",
    seconds: float = 1.0,
    settings: dict[str, Any] | None = None,
) -> PluginRun:
    """Run ``config`` for ``seconds`` with ``plugin`` as ``name``; what it produced."""
    with running(config, plugin, name, seconds, settings) as run:
        pass
    return run


try:
    import pytest
except ImportError:  # the harness needs no pytest; only the fixture does
    pass
else:

    @pytest.fixture
    def abh3_run() -> Callable[..., PluginRun]:
        """``run_with_plugin`` as a fixture: ``pytest_plugins = ["abh3_supervisor.plugin_testing"]``
        in your top-level conftest.py, then ``def test_x(abh3_run): abh3_run(yaml, plugin)``."""
        return run_with_plugin
