"""Finding, configuring and running plugins, each isolated from the bus and the others.

Plugins are found through the entry-point group ``abh3_supervisor`` (our built-ins too);
listing them imports nothing. Only plugins named in the YAML ``plugins:`` section are
loaded. Every hook call is isolated per plugin: an exception (in a hook, or uncaught in a
thread the plugin started) is logged with the plugin's name, and after ``MAX_FAILURES``
failures in one run — the first, under ``on_error: stop`` — the plugin is disabled; a
plugin disabled under ``on_error: stop`` or marked ``critical: true`` ends the run.
Observation hooks are queued to a worker thread per plugin, so a slow plugin never delays
the bus; when its queue is full, events for it are dropped and counted, never waited for,
and a hook that runs longer than ``STUCK_S`` is logged while it sticks. Every other call
(configure, schema, threads, start, input sources and their ``start()``, stop) runs on a
thread of its own at normal priority with a deadline, never on the main thread: a hook
that blocks cannot keep a stop signal from ending the program. A plugin that fails or
blocks while starting fails the run before any drive is commanded; one that blocks while
stopping (or in a hook, with its queue full) is abandoned, so the way out always ends.
``sys.exit()`` or ``KeyboardInterrupt`` raised by plugin code is that plugin's failure,
like any exception: off the main thread neither can be a real exit or Ctrl-C.
"""

from __future__ import annotations

import _thread
import asyncio
import dataclasses
import functools
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from types import TracebackType
from typing import Any, cast

import pluggy

from abh3_supervisor.config.model import Config
from abh3_supervisor.config.schema import ON_ERROR_VALUES
from abh3_supervisor.config.source import Section, Source
from abh3_supervisor.core.inputs import InputArbiter, InputSource
from abh3_supervisor.core.journal import Entry, Reader
from abh3_supervisor.core.supervisor import (
    EstopChange,
    FlagChange,
    Notice,
    OwnerChange,
    Supervisor,
)
from abh3_supervisor.errors import Abh3Error, ConfigError, PluginError, did_you_mean
from abh3_supervisor.plugin_host import hookspecs, inventory, tick, validate
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.view import SupervisorView
from abh3_supervisor.scheduler.core import FeedbackEvent, HealthEvent, StatusEvent

log = logging.getLogger(__name__)
GROUP = "abh3_supervisor"
MAX_FAILURES = 5
QUEUE_SIZE = 10_000
START_DEADLINE_S = 5.0  # abh3_start, abh3_input_sources and each source's start()
MAX_START_S = 600.0  # the most a plugin's start_timeout_s may give it (a slow board)
STOP_DEADLINE_S = 2.0  # abh3_stop per plugin; then it is abandoned
DRAIN_DEADLINE_S = 5.0  # every worker's queue together, on the way out
LEFTOVER_GRACE_S = 1.0  # threads (not daemons) a plugin left running, after the run
STUCK_S = 3.0  # a hook running longer is logged at once (the queue fills much later)
# a worker's batches start at least this far apart: a bus watched frame by frame, or
# several buses, release events far more often than once a period (one at 100 Hz)
SPACING_S = 0.010
# while the loop releases events about a spacing apart, the worker wakes by itself this
# long after the next release is due; "about": up to PACED_S, which such a wake-up finds
LAG_S = 0.001
PACED_S = SPACING_S + LAG_S
_STOP = object()
# what plugin code may raise that is its failure, not ours: every hook runs off the main
# thread, so sys.exit() and KeyboardInterrupt there end nothing but are the plugin's bug
RAISED = (Exception, SystemExit, KeyboardInterrupt)


class DeadlinePassed(Exception):
    """A plugin's hook did not return within its deadline: its failure. Not
    ``TimeoutError``, an ``OSError``: that would read as its output failing."""


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
        except Exception as exc:  # a broken plugin must not hide the others' schemas
            problems[name] = repr(exc)
            continue
        answers: list[dict[str, Any] | None] = []
        # like every hook: off the main thread with a deadline (a stop signal lands)
        ask = functools.partial(_ask_schema, pm, answers)
        problem = bounded(f"plugin {name} abh3_config_schema", START_DEADLINE_S, ask)
        if problem is not None:
            problems[name] = problem
            continue
        schemas[name] = answers[0] if answers else None
    return schemas, problems


def _ask_schema(pm: pluggy.PluginManager, answers: list[dict[str, Any] | None]) -> None:
    answers.extend(pm.hook.abh3_config_schema())


@dataclasses.dataclass
class _Call:
    """One bounded call of a plugin's hook: what it returned or raised, and what went
    wrong as said (None: it returned in time)."""

    answer: object = None
    error: BaseException | None = None
    problem: str | None = None


def _ignoring_result(caller: Any) -> Callable[..., object]:
    """One plugin's hook called for its effect only, as pluggy would call it: a plain
    implementation is called directly with the arguments it names. pluggy's own call
    (results gathered, wrappers run) was a quarter of the ROS 2 bridge's thread at
    hundreds of events a second; a wrapper or an optional keyword still goes through it."""
    impls = caller.get_hookimpls()
    if len(impls) != 1 or impls[0].wrapper or impls[0].hookwrapper or impls[0].kwargnames:
        return caller  # type: ignore[no-any-return]
    function, names = impls[0].function, impls[0].argnames

    def call(**kwargs: Any) -> object:
        try:
            args = [kwargs[name] for name in names]
        except KeyError as exc:  # as pluggy says it
            raise pluggy.HookCallError(f"hook call must provide argument {exc.args[0]!r}") from exc
        return function(*args)

    return call


def _sleep_until(when: float) -> None:
    rest = when - time.monotonic()
    if rest > 0:
        time.sleep(rest)


class _Worker:
    """One plugin's observation hooks, run in order on a thread of its own.

    The loop holds the events of one of its steps (:meth:`hold`) and hands them over
    together when the step is done (:meth:`release`); other threads (the tick's)
    :meth:`post`. Either appends to a bounded deque and wakes the thread only when it
    waits for work. At hundreds of events a second the thread (and the interpreter lock
    it takes from the loop) then runs once per step of the loop that had events — about
    once a bus period — instead of once per event, never in the middle of a step.
    Batches start at least ``SPACING_S`` apart: released sooner, the thread rests the
    remainder first (a watched bus steps once per frame; several buses step apart).
    While the loop releases about a spacing apart (a bus at 100 Hz), the thread does not
    wait to be woken: it sleeps until ``LAG_S`` after the next release is due (a
    spacing after the last) and finds the events there. A wake-up from another thread
    costs the waker an interrupt to the sleeper's processor: at 100 a second about half
    a point of a core on this VM, most of it the loop's (docs/performance.md, section
    12). When nothing is there (the step was late), it waits for the loop. A tick is
    queued when it comes: it may run before the events of a loop step in progress.
    """

    def __init__(self, host: PluginHost, name: str, *, start: bool = True) -> None:
        """``start``: False leaves the thread unstarted (a test steps its waits itself)."""
        self.host, self.name = host, name
        self.began = 0.0  # when this batch began (monotonic)
        self.released_at = -math.inf  # the loop's last release
        self.took = -math.inf  # the release the last batch began with
        # the last two batches began with releases about a spacing apart: the loop's pace
        self.paced = False
        self.items: deque[object] = deque()
        self.held: list[object] = []  # this step's events, on the loop: see release()
        self._wake = threading.Event()
        self._idle = False  # the thread waits for _wake: the next post sets it
        self.dropped = 0
        # the hook running now and since when (monotonic), for the stuck-hook watch
        self.busy: tuple[str, float] | None = None
        self.asked = False  # the end marker is queued
        self.thread = threading.Thread(target=self._run, name=f"plugin {name}", daemon=True)
        if start:
            self.thread.start()

    def post(self, hook: str, kwargs: dict[str, Any]) -> None:
        """Queued now, from any thread (never waits)."""
        if not self._put((hook, kwargs)):
            self._drop()

    def hold(self, hook: str, kwargs: dict[str, Any]) -> None:
        """On the loop: queued at the :meth:`release` after this step (never waits)."""
        if self._full():
            self._drop()
        else:
            self.held.append((hook, kwargs))

    def take(self, entries: list[Entry]) -> None:
        """On the loop: journal entries, with what was held, to the thread in one
        wake-up; what the bound has no room for is dropped and counted."""
        room = QUEUE_SIZE - len(self.items) - len(self.held)
        if len(entries) > room:
            self.held.extend(entries[: max(room, 0)])
            self.missed(len(entries) - max(room, 0))
        else:
            self.held.extend(entries)
        self.release()

    def missed(self, count: int) -> None:
        """``count`` events this plugin will never see (counted, said)."""
        if count > 0:
            self._drop(count)

    def release(self) -> None:
        """On the loop: the events held so far to the thread, in one wake-up."""
        if self.held:
            held, self.held = self.held, []
            self.items.extend(held)
            self.released_at = time.monotonic()
            self._kick()

    def _drop(self, count: int = 1) -> None:
        before, self.dropped = self.dropped, self.dropped + count
        if any(before < said <= self.dropped for said in (1, 100, 10_000)):
            log.warning("plugin %s is too slow: %d events dropped", self.name, self.dropped)

    def _full(self) -> bool:
        """The bound counts what is queued and what the loop holds for it."""
        return len(self.items) + len(self.held) >= QUEUE_SIZE

    def _put(self, item: object) -> bool:
        """Queue ``item`` unless the queue is full (never waits)."""
        if self._full():
            return False
        self.items.append(item)
        self._kick()
        return True

    def _kick(self) -> None:
        if self._idle:  # one wake-up; what follows gathers while the thread works
            self._idle = False
            self._wake.set()

    def _run(self) -> None:
        self.host.thread_setup(self.name in self.host.below_loop)
        items = self.items
        while True:
            self._next_batch()
            while items:
                item = items.popleft()
                if item is _STOP:
                    return
                if len(item) == 3:  # type: ignore[arg-type]  # a journal entry
                    call = self.host.translate(cast(Entry, item))
                    if call is None:
                        continue
                    hook, kwargs = call
                else:
                    hook, kwargs = cast(tuple[str, dict[str, Any]], item)
                self.busy = hook, time.monotonic()
                try:
                    self.host.call_one(self.name, hook, **kwargs)
                finally:
                    self.busy = None

    def _next_batch(self) -> None:
        """Until the next batch begins: the loop's next release, slept to while the
        releases come about a spacing apart, else waited for; and at least a spacing
        after the last batch began (what is released meanwhile joins this one)."""
        items = self.items
        found = False  # by sleeping to the next release
        if not items and self.paced:
            _sleep_until(self.released_at + SPACING_S + LAG_S)
            found = bool(items)
        if not items:
            self._idle = True
            if not items:  # an item appended before _idle was seen: no wait for it
                self._wake.wait()
            self._idle = False
            self._wake.clear()
        if not found:  # (else a second sleep of the first one's overshoot)
            _sleep_until(self.began + SPACING_S)
        self.began = time.monotonic()
        self.paced = self.released_at - self.took <= PACED_S
        self.took = self.released_at

    def ask_to_end(self) -> bool:
        """The end marker after what is queued (so files get their last rows); False
        while the queue is full (a stuck hook): never waited for."""
        if not self.asked:
            self.release()  # what the loop held goes first
            if not self._put(_STOP):
                return False
            self.asked = True
        return True

    def close(self, end: float) -> None:
        """Ends after its queue, or is left behind (a daemon thread) at ``end``
        (monotonic); the wait is sliced, so a signal is handled at once."""
        while self.thread.is_alive() and (left := end - time.monotonic()) > 0:
            self.ask_to_end()
            self.thread.join(min(left, 0.05))
        if self.thread.is_alive():
            busy = f" (in {self.busy[0]})" if self.busy is not None else ""
            log.warning(
                "plugin %s did not finish its queue in time%s: left behind", self.name, busy
            )


class PluginHost:
    def __init__(self, config: Config, available: dict[str, EntryPoint] | None = None) -> None:
        self.pm = pluggy.PluginManager(hookspecs.PROJECT)
        self.pm.add_hookspecs(hookspecs)
        self.failures: dict[str, int] = {}
        self.disabled: set[str] = set()
        self._callers: dict[tuple[str, str], Any] = {}
        self._ignoring: dict[tuple[str, str], Callable[..., object]] = {}  # call_one's
        self.workers: dict[str, _Worker] = {}
        self.sources: list[InputSource] = []
        self.arbiter: InputArbiter | None = None
        self._inputs_stopped = False
        self.started: list[str] = []  # plugins whose abh3_start ran: they get abh3_stop
        self.on_error: dict[str, str] = {}  # plugin → "continue" (default) or "stop"
        self.critical: set[str] = set()  # plugins whose being disabled ends the run
        self.why_disabled: dict[str, str] = {}  # plugin → why, for the run's last lines
        self.output_failures: dict[str, str] = {}  # plugin → its output's OSError (the exit code)
        self.ended_by: str | None = None  # why a plugin ended the run (on_error/critical)
        self._lock = threading.Lock()  # failures come from any thread
        self._modules: dict[str, set[str]] = {}  # module → the plugins (and sources) in it
        self._threads: dict[threading.Thread, str] = {}  # threads started while it started
        # the plugin whose start runs now, and the threads there were before it
        self._starting_now: tuple[str, set[threading.Thread]] | None = None
        self._excepthook: Callable[[threading.ExceptHookArgs], Any] | None = None
        self._watching = threading.Event()  # set: the stuck-hook watch ends
        # set by the runtime: end the run, drives stopped (an output failed, on_error: stop)
        self.request_stop: Callable[[str], None] | None = None
        # set by the runtime: end the run as a normal stop (a plugin's end_run, exit 0)
        self.end_run: Callable[[str], None] | None = None
        self.views: dict[str, SupervisorView] = {}  # what each plugin sees (plugin_host/view.py)
        self.tick_hz: dict[str, float] = {}
        self.start_s: dict[str, float] = {}  # start_timeout_s where given
        self.tickers: list[tick.Ticker] = []
        # run first on every thread plugins run on (and so inherited by the threads they
        # start); the runtime drops the bus loop's real-time priority there
        self.thread_setup: Callable[[bool], None] = lambda below_loop: None
        self.below_loop: set[str] = set()  # plugins whose threads asked for it (abh3_threads)
        self.demote: Callable[[int], None] = lambda native_id: None  # one thread to normal
        self._sup: Supervisor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._releasing = False  # a release of the journal's news to the workers is queued
        self._reader: Reader | None = None  # the workers' place in the journal
        self._missed = 0  # of the reader's misses, those told to the workers
        self._ending = False  # stop() has begun: the run's loop waits for it
        self.outputs: list[tuple[str, str]] = []  # (file, where it is set) plugins write
        self._load(config, installed() if available is None else available)

    # ------------------------------------------------------------ loading

    def _load(self, config: Config, available: dict[str, EntryPoint]) -> None:
        src = config.source or Source(config.file, {})
        for name in config.plugins:
            ep = available.get(name)
            if ep is None:
                names = ", ".join(sorted(available)) or "none"
                did = did_you_mean(name, sorted(available))
                src.error(
                    ("plugins", name),
                    f"no plugin named '{name}' is installed{did} (installed: {names})",
                )
                continue
            try:
                plugin = _plugin_object(ep)
                self.pm.register(plugin, name=name)
                validate.validate_plugin(src, name, plugin, config.plugins[name], self.pm)
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
        ``on_error``, ``critical``, ``start_timeout_s`` and ``tick_hz`` are the host's
        keys, valid in every section: the plugin never sees them. Its check runs like its
        start, off the main thread within its start deadline."""
        raw = config.plugins[name]
        self.tick_hz[name], raw = tick.take_rate(Section(src, ("plugins", name), raw, None))
        if isinstance(raw, dict) and any(key in raw for key in validate.HOST_KEYS):
            host = Section(src, ("plugins", name), raw, None)
            self.on_error[name] = host.choice("on_error", "continue", list(ON_ERROR_VALUES))
            if host.boolean("critical", False):
                self.critical.add(name)
            if host.has("start_timeout_s"):
                self.start_s[name] = host.number(
                    "start_timeout_s", START_DEADLINE_S, 0.0, MAX_START_S, lo_open=True
                )
            raw = {k: v for k, v in raw.items() if k not in validate.HOST_KEYS}
        if not self._has(name, "abh3_configure"):
            return
        section = Section(src, ("plugins", name), raw, None)
        deadline = self._start_deadline(name)
        call = self._bounded(name, "abh3_configure", deadline, section=section, config=config)
        if isinstance(call.error, ConfigError):  # its own problems, unless already collected
            src.problems.extend(p for p in call.error.problems if p not in src.problems)
        elif call.error is not None:
            src.error(
                ("plugins", name), f"plugin '{name}' cannot use these settings: {call.error!r}"
            )
        elif call.problem is not None:  # blocked: left behind (a daemon thread)
            src.error(
                ("plugins", name),
                f"plugin '{name}' did not finish checking its settings (abh3_configure): "
                f"{call.problem}",
            )

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
            caller = self.pm.subset_hook_caller(hook, remove_plugins=others)
            self._callers[key] = caller
            self._ignoring[key] = _ignoring_result(caller)
        return self._callers[key]

    def call_one(self, name: str, hook: str, **kwargs: Any) -> None:
        """Call one plugin's implementation of ``hook``, isolated (any thread)."""
        if name in self.disabled:
            return
        try:
            if (call := self._ignoring.get((name, hook))) is None:
                self._caller(name, hook)  # builds it (a hook start() did not build)
                call = self._ignoring[name, hook]
            call(**kwargs)
        except ConfigError:
            raise
        except RAISED as exc:  # sys.exit() in a hook ends no thread of ours
            self._failed(name, hook, exc)

    def _failed(self, name: str, hook: str, exc: BaseException) -> None:
        """Any thread. Counted; disabled at ``MAX_FAILURES`` (at once under on_error:
        stop); an output's OSError disables it at once (its file is gone)."""
        if isinstance(exc, OSError):
            self._output_failed(name, exc)
            return
        with self._lock:
            count = self.failures[name] = self.failures.get(name, 0) + 1
        limit = 1 if self.on_error.get(name) == "stop" else MAX_FAILURES
        log.error(
            "plugin %s failed in %s (failure %d of %d): %r",
            name,
            hook,
            count,
            limit,
            exc,
            # a deadline passed has no traceback to show
            exc_info=exc if count == 1 and exc.__traceback__ is not None else None,
        )
        self._notice(f"plugin {name} failed in {hook}: {exc!r}")
        if count >= limit:
            self._disable(name, f"{count} failure(s), the last in {hook}: {exc!r}")

    def _notice(self, message: str, level: int = logging.ERROR) -> bool:
        """An operator's notice from any thread (the supervisor is only touched on its
        loop); False when there is no running supervisor to take it (on the way out the
        loop waits for :meth:`stop`: a notice would come after the last lines, if ever)."""
        if self._sup is None or self._loop is None or self._ending:
            return False
        try:
            self._loop.call_soon_threadsafe(self._sup.notice, None, level, message)
        except RuntimeError:  # the loop closed: the run is over
            return False
        return True

    def _disable(self, name: str, why: str) -> bool:
        """Any thread: the plugin is called no more; the run ends if its policy says so
        (on_error: stop, critical: true). False if it was disabled already."""
        with self._lock:
            if name in self.disabled:
                return False
            self.disabled.add(name)
            self.why_disabled[name] = why
        policy = self._policy(name)
        if policy is None:
            log.error("plugin %s disabled (%s); the others keep running", name, why)
            return True
        ending = f"plugin {name} was disabled ({why}; {policy})"
        log.error("%s: ending the run, drives stopped", ending)
        if self.ended_by is None:
            self.ended_by = ending
        if self.request_stop is not None:
            self.request_stop(ending)
        return True

    def _start_deadline(self, name: str) -> float:
        """How long plugin ``name``'s start may take: its ``start_timeout_s``, else 5 s."""
        return self.start_s.get(name, START_DEADLINE_S)

    def _policy(self, name: str) -> str | None:
        """What makes the plugin's being disabled end the run, or None."""
        if self.on_error.get(name) == "stop":
            return "on_error: stop"
        return "critical: true" if name in self.critical else None

    def _bounded(self, name: str, hook: str, deadline: float, **kwargs: Any) -> _Call:
        """Run one plugin's hook with a deadline (see :func:`bounded`), keeping what it
        answered or raised."""
        call = _Call()

        def run() -> None:
            try:
                call.answer = self._caller(name, hook)(**kwargs)
            except RAISED as exc:
                call.error = exc
                raise  # said by bounded()

        call.problem = self._starting(name, f"plugin {name} {hook}", deadline, run)
        return call

    def _starting(
        self, name: str, label: str, deadline: float, fn: Callable[[], object]
    ) -> str | None:
        """``fn`` (plugin ``name``'s code) on a thread at normal priority with a deadline;
        threads that appear meanwhile are the plugin's (their exceptions name it)."""
        before = set(threading.enumerate())
        self._starting_now = name, before
        try:
            problem = bounded(label, deadline, self._normal(fn, name in self.below_loop))
        finally:
            self._starting_now = None
        for thread in set(threading.enumerate()) - before:
            if thread.name != label:  # bounded's own
                self._threads[thread] = name
        return problem

    def _output_failed(self, name: str, exc: OSError, hook: str | None = None) -> None:
        """Its output failed (disk full): one clear line, no traceback, once; the plugin
        writes no more; the run goes on, or ends with the drives stopped under on_error:
        stop (or critical: true). In ``abh3_stop`` (``hook``) the run is ending already:
        it decides the exit code only (5, docs/plugins.md)."""
        late = self._ending
        with self._lock:
            if name in self.output_failures:
                return
            self.output_failures[name] = str(exc)
            switched_off = name not in self.disabled and not late
            if switched_off:
                self.disabled.add(name)
                self.why_disabled[name] = f"output failed: {exc}"
        policy = self._policy(name) if switched_off else None
        if late:
            outcome = "the run was ending already"
        elif policy is not None:
            outcome = f"stopping the run ({policy})"
        else:
            outcome = "it is switched off; the run goes on (on_error: continue)"
        where = f" in {hook}" if hook is not None else ""
        message = f"plugin {name}: output failed{where}: {exc}; {outcome}"
        if not self._notice(message):  # the operator's log (headless, TUI) shows notices
            log.error("%s", message)
        if policy is not None:
            ending = f"the output of plugin {name} failed ({policy})"
            if self.ended_by is None:
                self.ended_by = ending
            if self.request_stop is not None:
                self.request_stop(ending)

    def _end_run(self, why: str) -> None:
        """A plugin's view asks to end the run normally (from any thread)."""
        if self.end_run is not None:
            self.end_run(why)

    def _threads_below_loop(self, name: str) -> bool:
        """The plugin's ``abh3_threads`` answer, asked like its start: off the loop (the
        main thread, where a stop signal must land) within its start deadline. Anything but
        ``"below_loop"`` leaves its threads at normal priority; a raise (``sys.exit()``
        too) or a block is the plugin's failure, counted under its ``on_error``; one that
        ends the run (``on_error: stop``, ``critical``) fails it before any frame."""
        if not self._has(name, "abh3_threads"):
            return False
        call = self._bounded(name, "abh3_threads", self._start_deadline(name))
        if call.problem is None:
            return hookspecs.THREADS_BELOW_LOOP in cast(list[object], call.answer)
        error = call.error if call.error is not None else DeadlinePassed(call.problem)
        self._failed(name, "abh3_threads", error)  # else its threads: normal priority
        if name in self.disabled and self._policy(name) is not None:
            raise PluginError(f"plugin {name} could not start (abh3_threads): {call.problem}")
        return False

    def _has(self, name: str, hook: str) -> bool:
        caller = getattr(self.pm.hook, hook)
        return any(impl.plugin_name == name for impl in caller.get_hookimpls())

    # ------------------------------------------------------------ lifecycle

    def start(self, sup: Supervisor, loop: asyncio.AbstractEventLoop) -> None:
        self._sup, self._loop = sup, loop
        log.info("%s", inventory.loaded_line(self.names, installed()))
        self._excepthook = threading.excepthook
        threading.excepthook = self._thread_failed
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
            self._modules.setdefault(type(self.pm.get_plugin(name)).__module__, set()).add(name)
            for hook in observing:
                self._caller(name, hook)
            if self._threads_below_loop(name):
                self.below_loop.add(name)
        owners: dict[int, str] = {}  # source (by id) → the plugin that registered it
        for name in self.names:
            self.started.append(name)  # even if it fails half way: it may hold resources
            view = self.views[name] = SupervisorView(sup, loop, name, self._end_run)

            def register(source: InputSource, name: str = name) -> None:
                owners[id(source)] = name
                self.sources.append(source)

            for hook, kwargs in (
                ("abh3_start", {"supervisor": view}),
                ("abh3_input_sources", {"register": register, "supervisor": view}),
            ):
                deadline = self._start_deadline(name)
                problem = self._bounded(name, hook, deadline, **kwargs).problem
                if problem is not None:  # the user asked for it: run without it, never
                    raise PluginError(f"plugin {name} could not start ({hook}): {problem}")
            if any(self._has(name, hook) for hook in observing):
                self.workers[name] = _Worker(self, name)
        for name, worker in self.workers.items():
            if self._has(name, tick.HOOK):
                hz = self.tick_hz.get(name, tick.DEFAULT_HZ)
                setup = functools.partial(self.thread_setup, name in self.below_loop)
                ticker = tick.Ticker(name, hz, sup.clock, worker.post, setup)
                self.tickers.append(ticker)
        self._reader = sup.journal.reader()
        sup.watchers.append(self._news)
        self._start_inputs(sup, loop, owners)  # always: service clients may attach later
        if self.workers:
            threading.Thread(target=self._watch, name="plugin watch", daemon=True).start()

    def _start_inputs(
        self, sup: Supervisor, loop: asyncio.AbstractEventLoop, owners: dict[int, str]
    ) -> None:
        """The plugins' sources join the supervisor's arbitration (core/inputs.py), each
        started like a plugin: off the loop, at normal priority, with a deadline; one
        that fails or blocks fails the run before any drive is commanded."""
        arbiter = self.arbiter = sup.arbiter
        for source in self.sources:
            unknown = [u for u in source.units if u not in sup.units]
            if unknown:
                log.error("input %s names unknown units %s: not started", source.name, unknown)
                continue
            arbiter.add(source)
            feed = InputFeed(loop, arbiter, source.name, sup)
            owner = owners.get(id(source))
            if owner is None:  # the host program's own (the TUI's): ours, on the loop
                source.start(feed)
                continue
            self._modules.setdefault(type(source).__module__, set()).add(owner)
            label = f"input {source.name} start"
            start = functools.partial(source.start, feed)
            problem = self._starting(owner, label, self._start_deadline(owner), start)
            if problem is not None:  # like a plugin that cannot start: the run fails
                raise PluginError(
                    f"plugin {owner} could not start (input {source.name}): {problem}"
                )

    def _normal(self, fn: Callable[[], object], below_loop: bool = False) -> Callable[[], object]:
        """``fn`` run at normal priority, or just below the loop's for a plugin that asked
        (plugin code, on a thread of its own)."""

        def call() -> object:
            self.thread_setup(below_loop)
            return fn()

        return call

    def _thread_failed(self, args: threading.ExceptHookArgs) -> None:
        """An exception nobody caught in a thread: a plugin's (one it started while
        starting, or running its code) is that plugin's failure, named; else as before."""
        name = self._owner(args.thread, args.exc_traceback)
        if name is None or args.exc_value is None or args.exc_type is SystemExit:
            if self._excepthook is not None:
                self._excepthook(args)
            return
        thread = args.thread.name if args.thread is not None else "?"
        self._failed(name, f"its thread {thread!r}", args.exc_value)

    def _owner(self, thread: threading.Thread | None, tb: TracebackType | None) -> str | None:
        if thread is not None and thread in self._threads:
            return self._threads[thread]
        starting = self._starting_now  # one that fails before its start returned
        if thread is not None and starting is not None and thread not in starting[1]:
            return starting[0]
        while tb is not None:  # the plugin's code on the way to the exception
            names = self._modules.get(tb.tb_frame.f_globals.get("__name__", ""), set())
            if len(names) == 1:  # one module, one plugin: not the host's guess
                return next(iter(names))
            tb = tb.tb_next
        return None

    def _watch(self) -> None:
        """A hook that sticks is said while it sticks (the queue fills much later), and
        its thread goes back to normal priority: a real-time thread spinning would keep
        the machine's other programs off a core."""
        said: dict[str, float] = {}  # plugin → the start of the call already said
        while not self._watching.wait(min(STUCK_S / 4, 0.5)):
            now = time.monotonic()
            for name, worker in list(self.workers.items()):
                busy = worker.busy
                if busy is None or now - busy[1] < STUCK_S or said.get(name) == busy[1]:
                    continue
                said[name] = busy[1]
                message = (
                    f"plugin {name} is stuck in {busy[0]} for {now - busy[1]:.1f} s: its "
                    "events queue up (then are dropped); the bus is not affected"
                )
                log.warning("%s", message)
                self._notice(message, logging.WARNING)
                if name in self.below_loop and worker.thread.native_id is not None:
                    self.demote(worker.thread.native_id)

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

    def _news(self) -> None:
        """On the loop, once per step that wrote events: the workers get them from the
        journal after this step (:meth:`_release`)."""
        if not self._releasing and self.workers:
            assert self._loop is not None
            self._releasing = True
            self._loop.call_soon(self._release)

    def _release(self) -> None:
        """On the loop, once per step that wrote events: what the journal has since the
        last release, to every worker in one wake-up (each translates it on its thread)."""
        self._releasing = False
        if self._reader is None:
            return
        entries = self._reader.read()
        missed, self._missed = self._reader.missed - self._missed, self._reader.missed
        for worker in self.workers.values():
            worker.missed(missed)
            worker.take(entries)

    def translate(self, entry: Entry) -> tuple[str, dict[str, Any]] | None:
        """A journal entry as the hook call it makes (None: no hook), on a worker."""
        _, event, sample = entry
        if isinstance(event, FeedbackEvent):
            feedback, setpoint, inputs = sample
            if feedback is None or feedback.t != event.t:  # an answer it could not read
                return None
            return "abh3_feedback", {
                "unit": event.unit,
                "feedback": feedback,
                "setpoint": setpoint,
                "inputs": inputs,
            }
        if isinstance(event, StatusEvent):
            return "abh3_status", {
                "unit": event.unit,
                "packet": event.packet,
                "record": event.record,
                "t": event.t,
            }
        if isinstance(event, HealthEvent):
            return "abh3_health", {"unit": event.unit, "online": event.online, "t": event.t}
        if isinstance(event, FlagChange):
            return "abh3_flags", {"change": event}
        if isinstance(event, Notice):
            return "abh3_notice", {"notice": event}
        if isinstance(event, EstopChange):
            return "abh3_estop", {"event": event}
        if isinstance(event, OwnerChange):
            return "abh3_owner", {"change": event}
        return None

    def stop_inputs(self) -> None:
        """First on the way out: no input may command anything after this. Idempotent."""
        if self._inputs_stopped:
            return
        self._inputs_stopped = True
        if self.arbiter is not None:
            self.arbiter.closed = True  # calls still queued are dropped

    def stop(self, sup: Supervisor, timeout: float | None = None) -> None:
        """Last on the way out (drives already stopped): input sources let go of their
        devices, queues drain (``timeout`` for all), then abh3_stop — each with a
        deadline, so a plugin stuck anywhere delays the others' stop, never prevents it."""
        self.stop_inputs()
        self._ending = True
        for source in self.sources:  # after the stop frames: a source stuck here delays
            problem = bounded(
                f"input {source.name} stop", STOP_DEADLINE_S, self._normal(source.stop)
            )
            if problem is not None:  # nothing that moves a motor
                log.error("input %s failed to stop: %s", source.name, problem)
        self._watching.set()
        for ticker in self.tickers:
            ticker.close()
        self.tickers.clear()
        self._release()  # the journal's last events (the stop's) before the end marker
        for worker in self.workers.values():
            worker.ask_to_end()  # all drain together
        end = time.monotonic() + (DRAIN_DEADLINE_S if timeout is None else timeout)
        for worker in self.workers.values():
            worker.close(end)
        self.workers.clear()
        for name in self.started:
            view = self.views[name]  # made before its abh3_start
            call = self._bounded(name, "abh3_stop", STOP_DEADLINE_S, supervisor=view)
            if isinstance(call.error, OSError):  # its last rows lost: exit 5, as in the run
                self._output_failed(name, call.error, "abh3_stop")
            elif call.problem is not None:
                log.error("plugin %s failed in abh3_stop: %s", name, call.problem)
        if self._excepthook is not None and threading.excepthook == self._thread_failed:
            threading.excepthook = self._excepthook  # what plugins left behind: as before

    def leftovers(self, grace: float = LEFTOVER_GRACE_S) -> list[str]:
        """After the run: the threads (not daemons) still running ``grace`` seconds on,
        each named with its plugin where known. They would hold the interpreter's exit
        forever (it joins them), so the caller exits without them."""
        end = time.monotonic() + grace
        main = threading.main_thread()

        def running() -> list[threading.Thread]:
            return [
                t
                for t in threading.enumerate()
                if t is not main and t is not threading.current_thread() and not t.daemon
            ]

        while (left := running()) and time.monotonic() < end:
            left[0].join(min(end - time.monotonic(), 0.05))  # sliced: a signal lands
        owners = {t: self._owner(t, None) for t in left}
        return [
            f"thread {t.name!r}" + (f" of plugin {owners[t]}" if owners[t] else "") for t in left
        ]


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
        except RAISED as exc:  # sys.exit() is no success either
            # ours (a plugin's PluginError: a user's mistake) as said; anything else, its repr
            failure.append(str(exc) if isinstance(exc, Abh3Error) else repr(exc))
            log.debug("%s failed", label, exc_info=True)
        finally:
            done.release()

    threading.Thread(target=run, name=label, daemon=True).start()
    end = time.monotonic() + deadline
    while (left := end - time.monotonic()) > 0:
        if done.acquire(timeout=min(left, 0.05)):
            return failure[0] if failure else None
    return f"did not return within {deadline:g} s"
