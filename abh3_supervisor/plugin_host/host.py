"""Finding, configuring and running plugins, each isolated from the bus and the others.

Plugins are found through the entry-point group ``abh3_supervisor`` (our built-ins too);
listing them imports nothing. Only plugins named in the YAML ``plugins:`` section are
loaded. Every hook call is isolated per plugin: an exception is logged with the plugin's
name, and after ``MAX_FAILURES`` failures in one run the plugin is disabled. Observation
hooks are queued to a worker thread per plugin, so a slow plugin never delays the bus;
when its queue is full, events for it are dropped and counted, never waited for.
Lifecycle hooks (start, input sources, stop) run on a thread of their own with a deadline:
a plugin that fails or blocks while starting fails the run before any drive is commanded;
one that blocks while stopping is abandoned, so the way out always ends.
"""

from __future__ import annotations

import _thread
import asyncio
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any, cast

import pluggy

from abh3_supervisor.config.model import Config
from abh3_supervisor.config.schema import ON_ERROR_VALUES
from abh3_supervisor.config.source import Section, Source
from abh3_supervisor.core.inputs import InputArbiter, InputFeed, InputSource
from abh3_supervisor.core.supervisor import (
    EstopChange,
    FlagChange,
    Notice,
    OwnerChange,
    Supervisor,
    SupervisorEvent,
)
from abh3_supervisor.errors import Abh3Error, ConfigError, PluginError
from abh3_supervisor.plugin_host import hookspecs, tick
from abh3_supervisor.plugin_host.view import SupervisorView
from abh3_supervisor.scheduler.core import FeedbackEvent, HealthEvent, StatusEvent

log = logging.getLogger(__name__)
GROUP = "abh3_supervisor"
MAX_FAILURES = 5
QUEUE_SIZE = 10_000
# what an output failure (an OSError: disk full, device gone) of a plugin does to the run
START_DEADLINE_S = 5.0  # abh3_start and abh3_input_sources, per plugin
STOP_DEADLINE_S = 2.0  # abh3_stop per plugin; then it is abandoned
_STOP = object()


def installed() -> dict[str, EntryPoint]:
    """Installed plugins by name, without importing any of them."""
    return {ep.name: ep for ep in entry_points(group=GROUP)}


def _plugin_object(ep: EntryPoint) -> object:
    target = ep.load()
    return target() if isinstance(target, type) else target


def section_schemas(
    available: dict[str, EntryPoint] | None = None,
) -> tuple[dict[str, dict[str, Any] | None], dict[str, str]]:
    """Every installed plugin's section schema (None: it gives none), and why the plugins
    that could not say (failed to load or raised) could not. Nothing is started."""
    schemas: dict[str, dict[str, Any] | None] = {}
    problems: dict[str, str] = {}
    for name, ep in sorted((installed() if available is None else available).items()):
        pm = pluggy.PluginManager(hookspecs.PROJECT)
        pm.add_hookspecs(hookspecs)
        try:
            pm.register(_plugin_object(ep), name=name)
            answers = pm.hook.abh3_config_schema()
        except Exception as exc:  # a broken plugin must not hide the others' schemas
            problems[name] = repr(exc)
            continue
        schemas[name] = answers[0] if answers else None
    return schemas, problems


class _Worker:
    """One plugin's observation hooks, run in order on a thread of its own."""

    def __init__(self, host: PluginHost, name: str) -> None:
        self.host, self.name = host, name
        self.queue: queue.Queue[object] = queue.Queue(QUEUE_SIZE)
        self.dropped = 0
        self.thread = threading.Thread(target=self._run, name=f"plugin {name}", daemon=True)
        self.thread.start()

    def post(self, hook: str, kwargs: dict[str, Any]) -> None:
        try:
            self.queue.put_nowait((hook, kwargs))
        except queue.Full:
            self.dropped += 1
            if self.dropped in (1, 100, 10_000):
                log.warning("plugin %s is too slow: %d events dropped", self.name, self.dropped)

    def _run(self) -> None:
        self.host.thread_setup()
        while (item := self.queue.get()) is not _STOP:
            hook, kwargs = cast(tuple[str, dict[str, Any]], item)
            self.host.call_one(self.name, hook, **kwargs)

    def close(self, timeout: float) -> None:
        """Let the worker finish what is queued (so files get their last rows), then end."""
        self.queue.put(_STOP)
        self.thread.join(timeout)
        if self.thread.is_alive():
            log.warning("plugin %s did not finish its queue within %.1f s", self.name, timeout)


class PluginHost:
    def __init__(self, config: Config, available: dict[str, EntryPoint] | None = None) -> None:
        self.pm = pluggy.PluginManager(hookspecs.PROJECT)
        self.pm.add_hookspecs(hookspecs)
        self.failures: dict[str, int] = {}
        self.disabled: set[str] = set()
        self._callers: dict[tuple[str, str], Any] = {}
        self.workers: dict[str, _Worker] = {}
        self.sources: list[InputSource] = []
        self.arbiter: InputArbiter | None = None
        self._inputs_stopped = False
        self.started: list[str] = []  # plugins whose abh3_start ran: they get abh3_stop
        self.on_error: dict[str, str] = {}  # plugin → "continue" (default) or "stop"
        self.output_failures: dict[str, str] = {}  # plugin → its output's OSError (the exit code)
        # set by the runtime: end the run, drives stopped (an output failed, on_error: stop)
        self.request_stop: Callable[[str], None] | None = None
        # set by the runtime: end the run as a normal stop (a plugin's end_run, exit 0)
        self.end_run: Callable[[str], None] | None = None
        self.views: dict[str, SupervisorView] = {}  # what each plugin sees (plugin_host/view.py)
        self.tick_hz: dict[str, float] = {}
        self.tickers: list[tick.Ticker] = []
        # run first on every thread plugins run on (and so inherited by the threads they
        # start); the runtime drops the bus loop's real-time priority there
        self.thread_setup: Callable[[], None] = lambda: None
        self._sup: Supervisor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.outputs: list[tuple[str, str]] = []  # (file, where it is set) plugins write
        self._load(config, installed() if available is None else available)

    # ------------------------------------------------------------ loading

    def _load(self, config: Config, available: dict[str, EntryPoint]) -> None:
        src = config.source or Source(config.file, {})
        for name in config.plugins:
            ep = available.get(name)
            if ep is None:
                names = ", ".join(sorted(available)) or "none"
                src.error(
                    ("plugins", name), f"no plugin named '{name}' is installed (installed: {names})"
                )
                continue
            try:
                plugin = _plugin_object(ep)
                self.pm.register(plugin, name=name)
            except Exception as exc:  # a broken plugin is the plugin's fault, said plainly
                src.error(("plugins", name), f"plugin '{name}' failed to load: {exc!r}")
        src.raise_if_problems()
        for name in config.plugins:
            if self.pm.get_plugin(name) is not None:
                self._configure(name, config, src)
        src.raise_if_problems()
        self.outputs = list(src.outputs)  # what the plugins will write, and where it is set

    def refuse_recording_onto_an_output(self, record: Path, units: Iterable[str]) -> None:
        """:class:`Abh3Error` if ``--record`` names a file a plugin writes: two writers
        would interleave in it (the recording that should hold the stop frames too)."""
        target = record.resolve()
        for text, where in self.outputs:
            names = units if "{unit}" in text else ("",)
            if any(Path(text.replace("{unit}", n)).resolve() == target for n in names):
                raise Abh3Error(
                    f"--record {record}: {where} writes that file too; two writers would "
                    "interleave in it: give the recording another name"
                )

    def _configure(self, name: str, config: Config, src: Source) -> None:
        """The plugin checks its own section (keys with section.only(...)); whatever it
        raises is a problem with that section, reported like the core's (`check` too).
        ``on_error`` is the host's key, valid in every section: the plugin never sees it."""
        raw = config.plugins[name]
        if isinstance(raw, dict) and "on_error" in raw:
            host = Section(src, ("plugins", name), raw, None)
            self.on_error[name] = host.choice("on_error", "continue", list(ON_ERROR_VALUES))
            raw = {k: v for k, v in raw.items() if k != "on_error"}
        self.tick_hz[name], raw = tick.take_rate(Section(src, ("plugins", name), raw, None))
        section = Section(src, ("plugins", name), raw, None)
        try:
            self._caller(name, "abh3_configure")(section=section, config=config)
        except ConfigError as exc:  # its own problems, unless already collected
            src.problems.extend(p for p in exc.problems if p not in src.problems)
        except Exception as exc:
            src.error(("plugins", name), f"plugin '{name}' cannot use these settings: {exc!r}")

    def add_source(self, source: InputSource) -> None:
        """An input source of the host program itself (the TUI), arbitrated like the rest."""
        self.sources.append(source)

    def register(self, plugin: object, name: str) -> None:
        """Register an already built plugin object (tests, embedding)."""
        self.pm.register(plugin, name=name)

    @property
    def names(self) -> list[str]:
        """Active plugins (registered and not disabled)."""
        return [
            n for n, p in self.pm.list_name_plugin() if p is not None and n not in self.disabled
        ]

    # ------------------------------------------------------------ calling

    def _caller(self, name: str, hook: str) -> Any:
        key = (name, hook)
        if key not in self._callers:  # built on the loop thread before workers exist
            others = [p for n, p in self.pm.list_name_plugin() if n != name and p is not None]
            self._callers[key] = self.pm.subset_hook_caller(hook, remove_plugins=others)
        return self._callers[key]

    def call_one(self, name: str, hook: str, **kwargs: Any) -> None:
        """Call one plugin's implementation of ``hook``, isolated (any thread)."""
        if name in self.disabled:
            return
        try:
            self._caller(name, hook)(**kwargs)
        except ConfigError:
            raise
        except Exception as exc:
            self._failed(name, hook, exc)

    def _failed(self, name: str, hook: str, exc: Exception) -> None:
        if isinstance(exc, OSError):
            self._output_failed(name, exc)
            return
        count = self.failures[name] = self.failures.get(name, 0) + 1
        log.error(
            "plugin %s failed in %s (failure %d of %d): %r",
            name,
            hook,
            count,
            MAX_FAILURES,
            exc,
            exc_info=count == 1,
        )
        if self._sup is not None and self._loop is not None and not self._loop.is_closed():
            # may run on a worker thread: the supervisor is only touched on its loop
            self._loop.call_soon_threadsafe(
                self._sup.notice, None, logging.ERROR, f"plugin {name} failed in {hook}: {exc!r}"
            )
        if count >= MAX_FAILURES and name not in self.disabled:
            self.disabled.add(name)  # a set add: safe from any thread; calls stop here
            log.error(
                "plugin %s disabled after %d failures; the others keep running", name, MAX_FAILURES
            )

    def _bounded(self, name: str, hook: str, deadline: float, **kwargs: Any) -> str | None:
        """Run one plugin's lifecycle hook with a deadline (see :func:`bounded`)."""

        def call() -> object:
            self.thread_setup()
            return self._caller(name, hook)(**kwargs)

        return bounded(f"plugin {name} {hook}", deadline, call)

    def _output_failed(self, name: str, exc: OSError) -> None:
        """Its output failed (disk full): one clear line, no traceback; the plugin writes
        no more; the run goes on, or ends with the drives stopped under on_error: stop."""
        if name in self.disabled:
            return
        self.disabled.add(name)
        self.output_failures[name] = str(exc)
        policy = self.on_error.get(name, "continue")
        outcome = (
            "stopping the run (on_error: stop)"
            if policy == "stop"
            else "it is switched off; the run goes on (on_error: continue)"
        )
        message = f"plugin {name}: output failed: {exc}; {outcome}"
        if self._sup is not None and self._loop is not None and not self._loop.is_closed():
            # the operator's log (headless, TUI) shows notices: said once, there
            self._loop.call_soon_threadsafe(self._sup.notice, None, logging.ERROR, message)
        else:
            log.error("%s", message)
        if policy == "stop" and self.request_stop is not None:
            self.request_stop(f"the output of plugin {name} failed (on_error: stop)")

    def _end_run(self, why: str) -> None:
        """A plugin's view asks to end the run normally (from any thread)."""
        if self.end_run is not None:
            self.end_run(why)

    def _has(self, name: str, hook: str) -> bool:
        caller = getattr(self.pm.hook, hook)
        return any(impl.plugin_name == name for impl in caller.get_hookimpls())

    # ------------------------------------------------------------ lifecycle

    def start(self, sup: Supervisor, loop: asyncio.AbstractEventLoop) -> None:
        self._sup, self._loop = sup, loop
        observing = (
            "abh3_feedback",
            "abh3_status",
            "abh3_health",
            "abh3_flags",
            "abh3_notice",
            "abh3_estop",
            "abh3_owner",
            tick.HOOK,
        )
        for name in self.names:
            for hook in observing:
                self._caller(name, hook)
        for name in self.names:
            self.started.append(name)  # even if it fails half way: it may hold resources
            view = self.views[name] = SupervisorView(sup, loop, name, self._end_run)
            for hook, kwargs in (
                ("abh3_start", {"supervisor": view}),
                ("abh3_input_sources", {"register": self.sources.append, "supervisor": view}),
            ):
                problem = self._bounded(name, hook, START_DEADLINE_S, **kwargs)
                if problem is not None:  # the user asked for it: run without it, never
                    raise PluginError(f"plugin {name} could not start ({hook}): {problem}")
            if any(self._has(name, hook) for hook in observing):
                self.workers[name] = _Worker(self, name)
        for name, worker in self.workers.items():
            if self._has(name, tick.HOOK):
                hz = self.tick_hz.get(name, tick.DEFAULT_HZ)
                ticker = tick.Ticker(name, hz, sup.clock, worker.post, self.thread_setup)
                self.tickers.append(ticker)
        sup.subscribe(self._observe)
        self._start_inputs(sup, loop)  # always: service clients may attach sources later

    def _start_inputs(self, sup: Supervisor, loop: asyncio.AbstractEventLoop) -> None:
        """The plugins' sources join the supervisor's arbitration (core/inputs.py)."""
        arbiter = self.arbiter = sup.arbiter
        for source in self.sources:
            unknown = [u for u in source.units if u not in sup.units]
            if unknown:
                log.error("input %s names unknown units %s: not started", source.name, unknown)
                continue
            arbiter.add(source)
            try:
                source.start(InputFeed(loop, arbiter, source.name, sup))
            except Exception as exc:
                log.error("input %s failed to start: %r", source.name, exc)

    def attach(self, source: InputSource) -> InputFeed | None:
        """A source that comes and goes during the run (a service client), on the loop;
        None once the inputs have stopped."""
        if self.arbiter is None or self.arbiter.closed or self._sup is None or self._loop is None:
            return None
        self.arbiter.add(source)
        feed = InputFeed(self._loop, self.arbiter, source.name, self._sup)
        source.start(feed)
        return feed

    def detach(self, name: str) -> None:
        """The source lets go (its units stop if it drove them) and is forgotten."""
        if self.arbiter is not None and self._loop is not None:
            self.arbiter.remove(name, self._loop.time())

    def _observe(self, event: SupervisorEvent) -> None:
        """On the loop: translate an event into hook calls and queue them, never block."""
        if not self.workers:
            return
        assert self._sup is not None
        if isinstance(event, FeedbackEvent):
            unit = self._sup.units[event.unit]
            if unit.feedback is None or unit.feedback.t != event.t:
                return
            hook, kwargs = (
                "abh3_feedback",
                {"unit": event.unit, "feedback": unit.feedback, "setpoint": unit.setpoint},
            )
        elif isinstance(event, StatusEvent):
            hook, kwargs = (
                "abh3_status",
                {"unit": event.unit, "packet": event.packet, "record": event.record, "t": event.t},
            )
        elif isinstance(event, HealthEvent):
            hook, kwargs = "abh3_health", {"unit": event.unit, "online": event.online, "t": event.t}
        elif isinstance(event, FlagChange):
            hook, kwargs = "abh3_flags", {"change": event}
        elif isinstance(event, Notice):
            hook, kwargs = "abh3_notice", {"notice": event}
        elif isinstance(event, EstopChange):
            hook, kwargs = "abh3_estop", {"event": event}
        elif isinstance(event, OwnerChange):
            hook, kwargs = "abh3_owner", {"change": event}
        else:
            return
        for worker in self.workers.values():
            worker.post(hook, kwargs)

    def stop_inputs(self) -> None:
        """First on the way out: no input may command anything after this. Idempotent."""
        if self._inputs_stopped:
            return
        self._inputs_stopped = True
        if self.arbiter is not None:
            self.arbiter.closed = True  # calls still queued are dropped

    def stop(self, sup: Supervisor, timeout: float = 5.0) -> None:
        """Last on the way out (drives already stopped): input sources let go of their
        devices, queues drain, then abh3_stop — each with a deadline."""
        self.stop_inputs()
        for source in self.sources:  # after the stop frames: a source stuck here delays
            problem = bounded(f"input {source.name} stop", STOP_DEADLINE_S, source.stop)
            if problem is not None:  # nothing that moves a motor
                log.error("input %s failed to stop: %s", source.name, problem)
        for ticker in self.tickers:
            ticker.close()
        self.tickers.clear()
        for worker in self.workers.values():
            worker.close(timeout)
        self.workers.clear()
        for name in self.started:
            view = self.views[name]  # made before its abh3_start
            problem = self._bounded(name, "abh3_stop", STOP_DEADLINE_S, supervisor=view)
            if problem is not None:
                log.error("plugin %s failed in abh3_stop: %s", name, problem)


def bounded(label: str, deadline: float, fn: Callable[[], object]) -> str | None:
    """Run ``fn`` on a thread of its own for at most ``deadline`` seconds; what went wrong,
    or None. What blocks is left behind (a daemon thread), so it can hold up neither the
    buses nor the way out; the wait is sliced so a signal is handled at once."""
    failure: list[str] = []
    # a bare lock, not Thread.join: a stop signal raised while we wait must land in this
    # code, not inside the threading module (where the CLI defers it)
    done = _thread.allocate_lock()
    done.acquire()

    def run() -> None:
        try:
            fn()
        except Exception as exc:
            failure.append(repr(exc))
            log.debug("%s failed", label, exc_info=True)
        finally:
            done.release()

    threading.Thread(target=run, name=label, daemon=True).start()
    end = time.monotonic() + deadline
    while (left := end - time.monotonic()) > 0:
        if done.acquire(timeout=min(left, 0.05)):
            return failure[0] if failure else None
    return f"did not return within {deadline:g} s"
