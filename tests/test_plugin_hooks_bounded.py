"""Every plugin hook runs off the main thread with a deadline, and whatever it raises —
``sys.exit()`` and ``KeyboardInterrupt`` too — is that plugin's failure (docs/plugins.md,
"Failure policy"): a hang in any hook leaves SIGTERM and SIGINT working, an exit in a
hook is said with the plugin's name, an output failure in ``abh3_stop`` is exit 5, and
``tick_hz`` is the host's key in every section.

The processes are waited for by what they print, with generous timeouts that only bound
a failing test (a hung process is killed and its output shown)."""

from __future__ import annotations

import asyncio
import logging
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any, NoReturn

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import ConfigError, PluginError
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import GROUP, PluginHost, section_schemas
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.headless import run_headless
from tests.support.rig import TWO_UNITS
from tests.support.safe_word import commands_to

pytestmark = pytest.mark.wallclock  # real time: runtimes, threads, processes

ROOT = Path(__file__).resolve().parent.parent
PATIENCE_S = 60.0  # bounds a failing test only: every wait below ends on a condition

# ---------------------------------------------------------------- in a process of its own

MISBEHAVING = """
import errno, os, sys, threading
from abh3_supervisor.plugin_host.hookspecs import hookimpl

def said(text):
    print(text, file=sys.stderr, flush=True)

def hang(hook):
    said(f"hangs: in {hook}")
    threading.Event().wait()  # the threading module's wait: where a raised signal is deferred

class HangsInThreads:
    @hookimpl
    def abh3_threads(self):
        hang("abh3_threads")

class HangsInConfigure:
    @hookimpl
    def abh3_configure(self, section):
        hang("abh3_configure")

class HangsInSchema:
    @hookimpl
    def abh3_config_schema(self):
        hang("abh3_config_schema")

class ExitsInThreads:
    @hookimpl
    def abh3_threads(self):
        sys.exit(3)

class ExitsInConfigure:
    @hookimpl
    def abh3_configure(self, section):
        sys.exit(3)

class InterruptsInThreads:
    @hookimpl
    def abh3_threads(self):
        raise KeyboardInterrupt

class InterruptsInConfigure:
    @hookimpl
    def abh3_configure(self, section):
        raise KeyboardInterrupt

class DiskFullInStop:
    @hookimpl
    def abh3_feedback(self):
        pass

    @hookimpl
    def abh3_stop(self):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "out.jsonl")

class Good:
    @hookimpl
    def abh3_feedback(self):
        pass

    @hookimpl
    def abh3_stop(self):
        said("good: stopped")
"""
KINDS = (
    "HangsInThreads", "HangsInConfigure", "HangsInSchema", "ExitsInThreads", "ExitsInConfigure",
    "InterruptsInThreads", "InterruptsInConfigure", "DiskFullInStop", "Good",
)  # fmt: skip
RUNNER = f"""
import sys
from importlib.metadata import EntryPoint
import abh3_supervisor.plugin_host.host as host
# each plugin's name: its class's, in lower case
host.installed = lambda: {{
    k.lower(): EntryPoint(k.lower(), "misbehaving:" + k, "abh3_supervisor") for k in {KINDS!r}
}}
# a signal sent while a hook hangs must find it hanging, however loaded the machine:
# no deadline passes first unless the section gives a short one (start_timeout_s)
host.START_DEADLINE_S = 600.0
from abh3_supervisor.clients.cli import main
sys.exit(main(sys.argv[1:]))
"""


class Abh3:
    """``abh3 ARGS`` with these plugins installed, its stderr read as it comes."""

    def __init__(self, tmp_path: Path, *args: str) -> None:
        (tmp_path / "misbehaving.py").write_text(MISBEHAVING)
        (tmp_path / "run.py").write_text(RUNNER)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, str(tmp_path / "run.py"), *args],
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
            env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"},
        )
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.lines.put(line)
        self.lines.put(None)

    def wait_for(self, text: str) -> None:
        """Until a line holds ``text``; fails (the process killed) if it never comes."""
        end = time.monotonic() + PATIENCE_S
        while not any(text in line for line in self.seen):
            try:
                line = self.lines.get(timeout=max(0.0, end - time.monotonic()))
            except queue.Empty:
                self.fail(f"no line with {text!r}")
            if line is None:
                self.fail(f"ended before a line with {text!r}")
            self.seen.append(line)

    def end(self) -> tuple[int, str]:
        """The exit code and everything it said; fails (killed) if it does not end."""
        try:
            code = self.proc.wait(PATIENCE_S)
        except subprocess.TimeoutExpired:
            self.fail("it did not end")
        while (line := self.lines.get(timeout=PATIENCE_S)) is not None:
            self.seen.append(line)
        return code, "".join(self.seen)

    def fail(self, why: str) -> NoReturn:
        self.proc.kill()
        self.proc.wait()
        pytest.fail(f"{why}:\n{''.join(self.seen)}")


def config_file(tmp_path: Path, sections: str) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(TWO_UNITS + "plugins:\n" + sections)
    return path


def run(tmp_path: Path, sections: str, *more: str) -> Abh3:
    config = config_file(tmp_path, sections)
    return Abh3(tmp_path, "run", str(config), "--headless", "--no-socket", *more)


def nothing_commanded(record: Path) -> bool:
    return not record.exists() or (
        commands_to(record, 1, Generation.G2021) == [] == commands_to(record, 3, Generation.G2023)
    )


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
@pytest.mark.parametrize("hook", ["abh3_threads", "abh3_configure"])
def test_a_signal_while_a_plugin_hangs_before_the_run_ends_it_at_once(
    tmp_path: Path, hook: str, sig: signal.Signals
) -> None:
    """Called on the main thread, the hook held the signal off for good: the CLI's
    handler defers a signal that lands inside the threading module (a wait) and asks
    again, forever. Only ``kill -9`` ended it."""
    kind = "hangsinthreads" if hook == "abh3_threads" else "hangsinconfigure"
    record = tmp_path / "r.log"
    abh3 = run(tmp_path, f"  good: {{}}\n  {kind}: {{}}\n", "--record", str(record))
    abh3.wait_for(f"hangs: in {hook}")
    abh3.proc.send_signal(sig)
    code, said = abh3.end()
    assert code == 128 + sig, said
    assert f"abh3: stopped by {sig.name} while starting; no drive was started" in said
    assert "Traceback" not in said and "Exception ignored" not in said
    assert nothing_commanded(record)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_while_a_plugin_s_schema_hangs_ends_abh3_schema(
    tmp_path: Path, sig: signal.Signals
) -> None:
    abh3 = Abh3(tmp_path, "schema")
    abh3.wait_for("hangs: in abh3_config_schema")
    abh3.proc.send_signal(sig)
    code, said = abh3.end()
    assert code == 128 + sig, said
    assert f"abh3: stopped by {sig.name}" in said and "Traceback" not in said


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_plugin_hanging_in_abh3_threads_past_its_deadline_fails_and_the_run_goes_on(
    tmp_path: Path, sig: signal.Signals
) -> None:
    """Its deadline passed, the run starts without waiting for it (its threads at normal
    priority; one failure of five); a signal then ends the run the normal way: every
    other plugin's abh3_stop, the stops confirmed, exit 0."""
    sections = "  hangsinthreads: {start_timeout_s: 0.3}\n  good: {}\n"
    abh3 = run(tmp_path, sections, "--status-interval", "0")
    abh3.wait_for("running 2 unit(s)")
    abh3.proc.send_signal(sig)
    code, said = abh3.end()
    assert code == 0, said
    assert (
        "plugin hangsinthreads failed in abh3_threads (failure 1 of 5): "
        "DeadlinePassed('did not return within 0.3 s')" in said
    )
    assert "good: stopped" in said and said.count("stop frame confirmed by the drive") == 2
    assert "Traceback" not in said


@pytest.mark.parametrize(
    ("kind", "raised"),
    [("exitsinconfigure", "SystemExit(3)"), ("interruptsinconfigure", "KeyboardInterrupt()")],
)
@pytest.mark.parametrize("command", ["run", "check"])
def test_an_exit_in_abh3_configure_is_a_problem_with_the_plugin_s_section(
    tmp_path: Path, kind: str, raised: str, command: str
) -> None:
    """As a raise there is: exit 2, file and line, the plugin named (it ended the process
    at once, exit 3, without a word)."""
    config = config_file(tmp_path, f"  {kind}: {{}}\n  good: {{}}\n")
    more = ("--headless", "--no-socket") if command == "run" else ()
    code, said = Abh3(tmp_path, command, str(config), *more).end()
    assert code == 2, said
    assert f"c.yaml:9: plugins.{kind}: plugin '{kind}' cannot use these settings: {raised}" in said
    assert "Traceback" not in said


@pytest.mark.parametrize(
    ("kind", "raised"),
    [("exitsinthreads", "SystemExit(3)"), ("interruptsinthreads", "KeyboardInterrupt()")],
)
def test_an_exit_in_abh3_threads_is_the_plugin_s_failure_and_the_run_goes_on(
    tmp_path: Path, kind: str, raised: str
) -> None:
    abh3 = run(tmp_path, f"  {kind}: {{}}\n  good: {{}}\n", "--duration", "0.5")
    code, said = abh3.end()
    assert code == 0, said  # one failure of five (on_error: continue)
    assert f"plugin {kind} failed in abh3_threads (failure 1 of 5): {raised}" in said
    assert "good: stopped" in said and said.count("stop frame confirmed by the drive") == 2


@pytest.mark.parametrize("section", ["{on_error: stop}", "{critical: true, on_error: stop}"])
def test_an_exit_in_abh3_threads_under_on_error_stop_fails_the_run_before_any_frame(
    tmp_path: Path, section: str
) -> None:
    record = tmp_path / "r.log"
    abh3 = run(tmp_path, f"  good: {{}}\n  exitsinthreads: {section}\n", "--record", str(record))
    code, said = abh3.end()
    assert code == 1, said
    assert "error: plugin exitsinthreads could not start (abh3_threads): SystemExit(3)" in said
    assert "plugin exitsinthreads failed in abh3_threads (failure 1 of 1): SystemExit(3)" in said
    assert nothing_commanded(record)


@pytest.mark.parametrize("policy", ["continue", "stop"])
def test_a_full_disk_in_abh3_stop_is_an_output_failure_exit_5(tmp_path: Path, policy: str) -> None:
    """docs/plugins.md and the README: an output stopped early on a write error is exit 5
    (it was 0: the error was only logged). The run was ending already, so on_error
    cannot end it sooner: 5 either way."""
    sections = f"  diskfullinstop: {{on_error: {policy}}}\n  good: {{}}\n"
    code, said = run(tmp_path, sections, "--duration", "0.5").end()
    assert code == 5, said
    assert (
        "plugin diskfullinstop: output failed in abh3_stop: [Errno 28] No space left on "
        "device: 'out.jsonl'; the run was ending already" in said
    )
    assert (
        "stopped early on a write error (the disk full?): plugin diskfullinstop's output; "
        "each holds what was written before that (exit code 5)" in said
    )
    assert "good: stopped" in said and "Traceback" not in said


# ---------------------------------------------------------------- in this process

RELEASE = threading.Event()  # set at each test's end: no thread outlives it blocked


@pytest.fixture(autouse=True)
def release_blocked() -> Iterator[None]:
    RELEASE.clear()
    yield
    RELEASE.set()


class BlocksInThreads:
    def __init__(self) -> None:
        self.entered = threading.Event()

    @hookimpl
    def abh3_threads(self) -> str:
        self.entered.set()
        RELEASE.wait(PATIENCE_S)  # before the fix it blocked the test itself: bounded
        return "below_loop"


class BlocksInConfigure:
    @hookimpl
    def abh3_configure(self) -> None:
        RELEASE.wait(PATIENCE_S)  # before the fix it blocked the test itself: bounded


class ExitsInSchema:
    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        sys.exit(3)


class DiskFull:
    """Its output fails during the run, and again as it closes."""

    @hookimpl
    def abh3_feedback(self) -> None:
        raise OSError(28, "No space left on device", "out.jsonl")

    @hookimpl
    def abh3_stop(self) -> None:
        raise OSError(28, "No space left on device", "out.jsonl")


class FailsInStop:
    @hookimpl
    def abh3_stop(self) -> None:
        raise ValueError("not an output")


class Ticks:
    """Implements abh3_tick and no abh3_configure."""

    def __init__(self) -> None:
        self.ticks: list[float] = []

    @hookimpl
    def abh3_tick(self, t: float) -> None:
        self.ticks.append(t)


def available(**plugins: type) -> dict[str, EntryPoint]:
    return {
        name: EntryPoint(name, f"{__name__}:{cls.__name__}", GROUP) for name, cls in plugins.items()
    }


def configured(sections: str, **plugins: type) -> tuple[Any, PluginHost]:
    config = parse_config(TWO_UNITS + "plugins:\n" + sections, "c.yaml")
    return config, PluginHost(config, available(**plugins))


def test_abh3_threads_runs_off_the_loop_s_thread_with_its_start_deadline(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The loop (the main thread) waits for it at most its deadline, where a signal
    lands; its answer then counts for nothing (normal priority)."""
    config, host = configured("  slow: {start_timeout_s: 0.2}\n", slow=BlocksInThreads)
    plugin = host.pm.get_plugin("slow")
    assert isinstance(plugin, BlocksInThreads)

    async def scenario() -> None:
        async with Runtime(config, plugins=host):
            assert plugin.entered.is_set()

    with caplog.at_level(logging.ERROR):
        asyncio.run(scenario())
    assert host.failures == {"slow": 1} and host.below_loop == set()
    assert (
        "plugin slow failed in abh3_threads (failure 1 of 5): "
        "DeadlinePassed('did not return within 0.2 s')" in caplog.text
    )
    assert "Traceback" not in caplog.text


@pytest.mark.parametrize("policy", ["on_error: stop", "critical: true, on_error: stop"])
def test_a_block_in_abh3_threads_under_on_error_stop_fails_the_start(policy: str) -> None:
    config, host = configured(f"  slow: {{start_timeout_s: 0.2, {policy}}}\n", slow=BlocksInThreads)

    async def scenario() -> None:
        async with Runtime(config, plugins=host):
            pytest.fail("the run began")

    with pytest.raises(PluginError, match=r"plugin slow could not start \(abh3_threads\): did"):
        asyncio.run(scenario())


def test_a_block_in_abh3_configure_is_a_problem_with_its_section() -> None:
    with pytest.raises(ConfigError) as caught:
        configured("  slow: {start_timeout_s: 0.2}\n", slow=BlocksInConfigure)
    assert caught.value.problems == [
        "c.yaml:9: plugins.slow: plugin 'slow' did not finish checking its settings "
        "(abh3_configure): did not return within 0.2 s"
    ]


def test_an_exit_in_abh3_config_schema_is_that_plugin_s_problem_only() -> None:
    schemas, problems = section_schemas(available(bad=ExitsInSchema, ticks=Ticks))
    assert problems == {"bad": "SystemExit(3)"}
    assert schemas == {"ticks": None}


def headless(config: Any, host: PluginHost) -> int:
    return asyncio.run(
        run_headless(config, duration=0.3, record=None, status_interval=0, plugins=host)
    )


def test_a_failure_in_abh3_stop_that_is_no_output_s_is_said_and_changes_no_exit_code(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config, host = configured("  bad: {}\n", bad=FailsInStop)
    with caplog.at_level(logging.INFO):
        assert headless(config, host) == 0
    assert "plugin bad failed in abh3_stop: ValueError('not an output')" in caplog.text


def test_a_full_disk_in_abh3_stop_after_the_output_failed_is_said_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config, host = configured("  full: {}\n", full=DiskFull)
    with caplog.at_level(logging.INFO):
        assert headless(config, host) == 5
    assert caplog.text.count("plugin full: output failed") == 1, caplog.text
    assert "plugin full: output failed: [Errno 28]" in caplog.text  # in the run, not the stop


def test_tick_hz_is_taken_from_a_plugin_without_abh3_configure() -> None:
    """docs/plugins.md: a host key of every section (it was refused as a setting of a
    plugin that takes none)."""
    config, host = configured("  ticks: {tick_hz: 50}\n", ticks=Ticks)
    plugin = host.pm.get_plugin("ticks")
    assert isinstance(plugin, Ticks)
    assert host.tick_hz["ticks"] == 50.0

    async def scenario() -> None:
        async with Runtime(config, plugins=host):
            assert [t.period for t in host.tickers] == [1 / 50]
            end = time.monotonic() + PATIENCE_S
            while len(plugin.ticks) < 3:
                assert time.monotonic() < end, "no ticks"
                await asyncio.sleep(0.01)

    asyncio.run(scenario())


@pytest.mark.parametrize(
    ("section", "problem"),
    [
        ("{tick_hz: 0}", "plugins.ticks.tick_hz"),
        ("{tick_hz: 20, rate: 1}", "plugins.ticks.rate: plugin 'ticks' takes no settings"),
    ],
)
def test_tick_hz_of_a_plugin_without_abh3_configure_is_checked_and_nothing_else_allowed(
    section: str, problem: str
) -> None:
    with pytest.raises(ConfigError) as caught:
        configured(f"  ticks: {section}\n", ticks=Ticks)
    assert any(problem in p for p in caught.value.problems), caught.value.problems


def test_every_host_key_is_allowed_without_abh3_configure() -> None:
    _, host = configured(
        "  ticks: {tick_hz: 5, on_error: stop, critical: true, start_timeout_s: 9}\n",
        ticks=Ticks,
    )
    assert host.tick_hz == {"ticks": 5.0} and host.on_error == {"ticks": "stop"}
    assert host.critical == {"ticks"} and host.start_s == {"ticks": 9.0}
