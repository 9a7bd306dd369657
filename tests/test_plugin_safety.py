"""A misbehaving plugin cannot leave a drive commanded or the process unkillable (issue 31):
each fault injected with a real plugin, judged by what the simulated drive got and by the
exit code and the last lines."""

from __future__ import annotations

import asyncio
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any, ClassVar

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Config
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.core.kinematics import ab_to_yx
from abh3_supervisor.core.supervisor import Notice, SupervisorEvent
from abh3_supervisor.errors import PluginError, RunError
from abh3_supervisor.plugin_host import host as plugin_host
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.hookspecs import THREADS_BELOW_LOOP, hookimpl
from abh3_supervisor.plugin_host.host import GROUP, MAX_FAILURES, PluginHost
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.runtime import priority
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.headless import run_headless
from abh3_supervisor.runtime.stopping import CONFIRMED
from tests.support.rig import TWO_UNITS
from tests.support.safe_word import assert_drive_stopped, assert_stopped_in, commands_to

pytestmark = pytest.mark.wallclock  # real time: runtimes, threads, processes

CONFIG = parse_config(TWO_UNITS, "t.yaml")
ROOT = Path(__file__).resolve().parent.parent


async def until(condition: Callable[[], bool], timeout: float = 10.0) -> None:
    """Wait (on the loop, which keeps running) until ``condition`` holds."""
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "the condition never held"
        await asyncio.sleep(0.01)


def available(**plugins: type) -> dict[str, EntryPoint]:
    """Plugins of this module as if installed (their sections read like any other's)."""
    return {
        name: EntryPoint(name, f"{__name__}:{cls.__name__}", GROUP) for name, cls in plugins.items()
    }


def configured(sections: str, **plugins: type) -> tuple[Config, PluginHost]:
    config = parse_config(TWO_UNITS + "plugins:\n" + sections, "c.yaml")
    return config, PluginHost(config, available(**plugins))


# ---------------------------------------------------------------- plugins that misbehave

RELEASE = threading.Event()  # set at each test's end: no thread outlives it blocked


@pytest.fixture(autouse=True)
def release_blocked() -> Iterator[None]:
    RELEASE.clear()
    yield
    RELEASE.set()


class StuckInFeedback:
    """Blocks in its first observation hook until the test ends."""

    def __init__(self) -> None:
        self.entered = threading.Event()

    @hookimpl
    def abh3_feedback(self) -> None:
        self.entered.set()
        RELEASE.wait()


class Records:
    """A well-behaved output: counts rows, and its abh3_stop must run."""

    def __init__(self) -> None:
        self.rows = 0
        self.stopped = False

    @hookimpl
    def abh3_feedback(self) -> None:
        self.rows += 1

    @hookimpl
    def abh3_stop(self) -> None:
        self.stopped = True


class Raises:
    """Fails in every observation."""

    @hookimpl
    def abh3_feedback(self) -> None:
        raise ValueError("broken plugin")


class ThreadRaises:
    """Starts a thread (as a plugin does in abh3_start) that fails."""

    @hookimpl
    def abh3_start(self) -> None:
        threading.Thread(target=self._spin, name="spinner", daemon=True).start()

    def _spin(self) -> None:
        raise RuntimeError("the plugin's thread fell over")


class LaterThreadRaises:
    """Starts a failing thread later, from a hook (not while starting)."""

    def __init__(self) -> None:
        self.once = threading.Lock()

    @hookimpl
    def abh3_feedback(self) -> None:
        if self.once.acquire(blocking=False):
            threading.Thread(target=_fall_over, name="late", daemon=True).start()


def _fall_over() -> None:
    raise KeyError("late")


def host_with(*plugins: tuple[str, object]) -> PluginHost:
    host = PluginHost(CONFIG)
    for name, plugin in plugins:
        host.register(plugin, name)
    return host


def drives(rt: Runtime) -> dict[str, Any]:
    return {"left": rt.sims["b"].drives[1], "right": rt.sims["b"].drives[3]}


# ---------------------------------------------------------------- stuck in a hook


def test_a_hook_stuck_with_its_queue_full_cannot_hold_the_way_out(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The end marker is never waited for on a full queue: the other plugin's abh3_stop
    runs and the runtime ends at the drain deadline, the drives stopped first."""
    monkeypatch.setattr(plugin_host, "QUEUE_SIZE", 3)
    monkeypatch.setattr(plugin_host, "DRAIN_DEADLINE_S", 0.3)
    stuck, good = StuckInFeedback(), Records()
    host = host_with(("stuck", stuck), ("good", good))
    rt = Runtime(CONFIG, plugins=host)

    async def scenario() -> None:
        async with rt:
            sup = rt.supervisor
            for text in ("SERVO ON ON", "START ON ON"):
                assert await sup.command("left", text) == ""
            await until(lambda: host.workers["stuck"].dropped > 0)  # its queue is full

    with caplog.at_level(logging.INFO):
        start = time.monotonic()
        asyncio.run(scenario())
        took = time.monotonic() - start
    assert rt.stop_report == {"left": CONFIRMED, "right": CONFIRMED}
    assert good.stopped and good.rows > 0
    assert_drive_stopped(drives(rt)["left"])
    assert "plugin stuck did not finish its queue in time (in abh3_feedback)" in caplog.text
    assert took < 10


def test_a_hook_that_sticks_is_said_at_once_not_when_the_queue_fills(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(plugin_host, "STUCK_S", 0.2)
    monkeypatch.setattr(plugin_host, "DRAIN_DEADLINE_S", 0.3)  # it stays stuck to the end
    stuck = StuckInFeedback()
    host = host_with(("stuck", stuck))
    rt = Runtime(CONFIG, plugins=host)
    notices: list[str] = []

    async def scenario() -> None:
        async with rt:
            rt.supervisor.subscribe(
                lambda e: notices.append(e.message) if isinstance(e, Notice) else None
            )
            await until(lambda: any("is stuck in abh3_feedback" in n for n in notices))
            assert host.workers["stuck"].dropped == 0  # said long before events are lost

    with caplog.at_level(logging.WARNING):
        asyncio.run(scenario())
    said = [r.getMessage() for r in caplog.records if "is stuck" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("plugin stuck is stuck in abh3_feedback for")


STUCK_PLUGIN = """
import sys, threading
from abh3_supervisor.plugin_host.hookspecs import THREADS_BELOW_LOOP, hookimpl

class Stuck:
    @hookimpl
    def abh3_feedback(self):
        print("stuck: entered", file=sys.stderr, flush=True)
        threading.Event().wait()

class Good:
    @hookimpl
    def abh3_feedback(self):
        pass

    @hookimpl
    def abh3_stop(self):
        print("good: stopped", file=sys.stderr, flush=True)
"""
RUN_WITH_STUCK = """
import sys
from importlib.metadata import EntryPoint
import abh3_supervisor.plugin_host.host as host
host.installed = lambda: {
    "stuck": EntryPoint("stuck", "stuckplugin:Stuck", "abh3_supervisor"),
    "good": EntryPoint("good", "stuckplugin:Good", "abh3_supervisor"),
}
host.QUEUE_SIZE = 5
host.DRAIN_DEADLINE_S = 1.0
from abh3_supervisor.clients.cli import main
sys.exit(main(sys.argv[1:]))
"""
MOVING = """
buses:
  b: {interface: virtual, channel: stuckhook, simulate: true}
units:
  - {name: u, abh3_id: 1, protocol: "2023", command_rate_hz: 50,
     broadcast: {mask: 0x03, rate_hz: 4}, startup: ["SERVO ON ON", "START ON ON", "VEL 300 20"]}
plugins:
  stuck: {}
  good: {}
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_ends_a_run_whose_plugin_is_stuck_with_its_queue_full(
    tmp_path: Path, sig: signal.Signals
) -> None:

    (tmp_path / "stuckplugin.py").write_text(STUCK_PLUGIN)
    (tmp_path / "run.py").write_text(RUN_WITH_STUCK)
    (tmp_path / "c.yaml").write_text(MOVING)
    record = tmp_path / "r.log"
    proc = subprocess.Popen(
        [sys.executable, str(tmp_path / "run.py"), "run", str(tmp_path / "c.yaml"),
         "--headless", "--no-socket", "--status-interval", "0", "--record", str(record)],
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"},
    )  # fmt: skip
    assert proc.stderr is not None
    seen = []
    full = started = False
    for line in proc.stderr:
        seen.append(line)
        full |= "plugin stuck is too slow: " in line  # its queue is full
        started |= "+AY_START" in line  # the drive runs the start-up's VEL
        if full and started:
            break
    else:
        pytest.fail("".join(seen))
    sent = time.monotonic()
    proc.send_signal(sig)
    try:
        code = proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    rest = proc.stderr.read()
    assert time.monotonic() - sent < 6, rest  # stop 1 s + drain 1 s + abh3_stop, not forever
    assert code == 0, rest
    assert "good: stopped" in rest and "stop frame confirmed by the drive" in rest
    assert "Traceback" not in rest
    sent_to = commands_to(record, 1, Generation.G2023)
    assert any((c.cmd_ay, c.cmd_bx) == (300.0, 20.0) for c in sent_to)  # it was moving
    assert_stopped_in(record, {1: Generation.G2023})  # its last command: the stop


# ---------------------------------------------------------------- garbage from a source


class Garbage(InputSource):
    """Commands 500 min⁻¹ a few times, then only invalid values until the test ends."""

    BAD: tuple[tuple[object, object], ...] = (
        (math.nan, 0.0), (math.inf, 0.0), ("100", 0.0), (None, 0.0), (0.0, [1]), (True, 0.0),
    )  # fmt: skip

    def __init__(self, timeout: float) -> None:
        super().__init__("garbage", ("left",), timeout=timeout)
        self.valid_sent = threading.Event()
        self.sent_bad = 0

    def start(self, feed: InputFeed) -> None:
        threading.Thread(target=self._run, args=(feed,), name="garbage", daemon=True).start()

    def _run(self, feed: InputFeed) -> None:
        for _ in range(3):
            feed.velocity(500.0, 0.0)
        self.valid_sent.set()
        while not RELEASE.is_set():
            for ay, bx in self.BAD:
                feed.velocity(ay, bx)  # type: ignore[arg-type]
                feed.twist(ay, bx)  # type: ignore[arg-type]
                self.sent_bad += 2
            RELEASE.wait(0.002)  # a source's own pace, not the test's synchronisation

    def stop(self) -> None:
        pass


class ProvidesGarbage:
    def __init__(self) -> None:
        self.source = Garbage(timeout=0.3)

    @hookimpl
    def abh3_input_sources(self, register: Any) -> None:
        register(self.source)


def test_invalid_values_are_refused_and_the_units_stop_as_when_silent(
    caplog: pytest.LogCaptureFixture,
) -> None:
    plugin = ProvidesGarbage()
    rt = Runtime(CONFIG, plugins=host_with(("garbage", plugin)))
    notices: list[str] = []
    setpoints: list[tuple[float, float]] = []  # (loop time, left's AY) at each change

    def watch(event: SupervisorEvent) -> None:
        if isinstance(event, Notice):
            notices.append(event.message)
        ay = rt.supervisor.units["left"].setpoint.ay
        if not setpoints or setpoints[-1][1] != ay:
            setpoints.append((rt.supervisor.clock(), ay))

    async def scenario() -> None:
        async with rt:
            sup = rt.supervisor
            sup.subscribe(watch)
            for text in ("SERVO ON ON", "START ON ON"):
                assert await sup.command("left", text) == ""
            left = drives(rt)["left"]
            await until(lambda: left.cmd_raw != (0, 0))  # the valid command reached it
            await until(lambda: left.cmd_raw == (0, 0) and plugin.source.sent_bad > 100)
            stopped = sup.clock()
            await until(lambda: sup.clock() > stopped + 1.2)  # garbage goes on: still zero
            assert left.cmd_raw == (0, 0)
            assert sup.arbiter.owner("left") is None

    with caplog.at_level(logging.INFO):
        asyncio.run(scenario())
    moving = [t for t, ay in setpoints if ay == 500.0]
    zero = [t for t, ay in setpoints if ay == 0.0 and moving and t > moving[0]]
    assert moving and zero
    held = zero[0] - moving[0]
    assert held < 0.3 + 0.1, held  # its timeout, as silence: garbage refreshed nothing
    refused = [n for n in notices if n.startswith("input garbage refused: ")]
    assert refused and "not finite numbers" in refused[0]
    assert len(refused) <= 3  # about 1.5 s of garbage: rate-limited to one a second
    assert plugin.source.sent_bad > 10 * len(refused)
    assert "more refused since the last notice" in "".join(refused[1:]) or len(refused) == 1


class AB(InputSource):
    def __init__(self) -> None:
        super().__init__("ab", ("left", "right"), timeout=5.0)
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        pass


class ProvidesAB:
    def __init__(self) -> None:
        self.source = AB()

    @hookimpl
    def abh3_input_sources(self, register: Any) -> None:
        register(self.source)


def test_velocity_ab_on_the_feed_is_converted_per_unit_model_as_the_source_s_command() -> None:
    """left runs the travel model (Y/X), right the motor model (A/B)."""
    plugin = ProvidesAB()
    rt = Runtime(CONFIG, plugins=host_with(("ab", plugin)))

    async def scenario() -> None:
        async with rt:
            sup = rt.supervisor
            assert plugin.source.feed is not None
            plugin.source.feed.velocity_ab(120.0, 80.0)
            await until(lambda: sup.arbiter.owner("right") == "ab")
            assert sup.arbiter.owner("left") == "ab"
            left, right = sup.units["left"].setpoint, sup.units["right"].setpoint
            assert (left.ay, left.bx) == pytest.approx(ab_to_yx(120.0, 80.0))
            assert (right.ay, right.bx) == pytest.approx((120.0, 80.0))

    asyncio.run(scenario())


# ---------------------------------------------------------------- priority and start()


class Priorities(InputSource):
    """Notes the scheduling policy of each place plugin code runs."""

    seen: ClassVar[dict[str, int]] = {}

    def __init__(self) -> None:
        super().__init__("prio", ("left",))

    def start(self, feed: InputFeed) -> None:
        self.seen["source start()"] = os.sched_getscheduler(0)
        thread = threading.Thread(target=self._note, args=("source's thread",), daemon=True)
        thread.start()
        thread.join()

    def _note(self, where: str) -> None:
        self.seen[where] = os.sched_getscheduler(0)

    def stop(self) -> None:
        self.seen["source stop()"] = os.sched_getscheduler(0)


class ProvidesPriorities:
    def __init__(self) -> None:
        self.source = Priorities()
        self.fed = threading.Event()

    @hookimpl
    def abh3_start(self) -> None:
        self.source.seen["abh3_start"] = os.sched_getscheduler(0)
        thread = threading.Thread(target=self.source._note, args=("abh3_start's thread",))
        thread.start()
        thread.join()

    @hookimpl
    def abh3_input_sources(self, register: Any) -> None:
        register(self.source)

    @hookimpl
    def abh3_feedback(self) -> None:
        self.source.seen["abh3_feedback"] = os.sched_getscheduler(0)
        self.fed.set()


def test_plugin_code_runs_at_normal_priority_whatever_the_bus_loop_runs_at() -> None:
    """The bus loop at SCHED_FIFO as the runtime sets it (SCHED_BATCH stands in where
    real-time is not allowed: the policy a thread inherits is what is tested)."""
    fifo = priority._may_realtime()
    policy = os.SCHED_FIFO if fifo else os.SCHED_BATCH
    param = os.sched_param(priority.FIFO_PRIORITY if fifo else 0)
    plugin = ProvidesPriorities()
    Priorities.seen = {}
    loop_policy: list[int] = []
    failure: list[BaseException] = []

    async def scenario() -> None:
        rt = Runtime(CONFIG, plugins=host_with(("prio", plugin)))
        async with rt:
            loop_policy.append(os.sched_getscheduler(0))
            await until(plugin.fed.is_set)

    def bus_loop() -> None:
        try:
            os.sched_setscheduler(0, policy, param)  # this thread only (ends with it)
            asyncio.run(scenario())
        except BaseException as exc:
            failure.append(exc)

    thread = threading.Thread(target=bus_loop)
    thread.start()
    thread.join(30)
    assert not failure, failure
    assert loop_policy == [policy]
    expected = ["abh3_start", "abh3_start's thread", "source start()", "source's thread"]
    assert {*expected, "abh3_feedback", "source stop()"} <= set(Priorities.seen)
    assert set(Priorities.seen.values()) == {os.SCHED_OTHER}, Priorities.seen


class BelowLoop:
    """Asks for its threads below the loop; notes (policy, priority) where its code runs."""

    def __init__(self) -> None:
        self.seen: dict[str, tuple[int, int]] = {}
        self.fed, self.ticked = threading.Event(), threading.Event()

    def _note(self, where: str) -> None:
        self.seen[where] = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority

    @hookimpl
    def abh3_threads(self) -> str:
        return THREADS_BELOW_LOOP

    @hookimpl
    def abh3_start(self) -> None:
        self._note("abh3_start")
        thread = threading.Thread(target=self._note, args=("abh3_start's thread",))
        thread.start()
        thread.join()

    @hookimpl
    def abh3_feedback(self) -> None:
        self._note("abh3_feedback")
        self.fed.set()

    @hookimpl
    def abh3_tick(self) -> None:
        self._note("abh3_tick")
        self.ticked.set()


class StuckBelowLoop(BelowLoop):
    """Spins in its first feedback hook, noting its policy, until put back to normal."""

    @hookimpl
    def abh3_feedback(self) -> None:
        self._note("stuck, first")
        while os.sched_getscheduler(0) != os.SCHED_OTHER and not RELEASE.wait(0.01):
            pass
        self._note("stuck, last")
        self.fed.set()
        RELEASE.wait()


def on_a_real_time_loop(scenario: Callable[[], Any]) -> None:
    """``scenario`` (a coroutine function) on a loop thread at SCHED_FIFO, as abh3 run."""
    failure: list[BaseException] = []

    def bus_loop() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority.FIFO_PRIORITY))
            asyncio.run(scenario())
        except BaseException as exc:
            failure.append(exc)

    thread = threading.Thread(target=bus_loop)
    thread.start()
    thread.join(30)
    assert not failure, failure


@pytest.mark.skipif(not priority._may_realtime(), reason="needs root or RLIMIT_RTPRIO")
def test_a_plugin_that_asks_runs_every_thread_just_below_the_loop_and_no_other_does() -> None:
    asking, other = BelowLoop(), ProvidesPriorities()
    Priorities.seen = {}

    async def scenario() -> None:
        async with Runtime(CONFIG, plugins=host_with(("asks", asking), ("prio", other))):
            await until(lambda: asking.fed.is_set() and asking.ticked.is_set())
            await until(other.fed.is_set)

    on_a_real_time_loop(scenario)
    below = (os.SCHED_FIFO, priority.BELOW_LOOP_PRIORITY)
    assert asking.seen == dict.fromkeys(
        ["abh3_start", "abh3_start's thread", "abh3_feedback", "abh3_tick"], below
    )
    assert 0 < priority.BELOW_LOOP_PRIORITY < priority.FIFO_PRIORITY
    assert set(Priorities.seen.values()) == {os.SCHED_OTHER}, Priorities.seen  # the other's


@pytest.mark.skipif(not priority._may_realtime(), reason="needs root or RLIMIT_RTPRIO")
def test_a_real_time_hook_that_sticks_is_put_back_to_normal_priority(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A spinning real-time thread would keep the machine's programs off a core."""
    monkeypatch.setattr(plugin_host, "STUCK_S", 0.2)
    monkeypatch.setattr(plugin_host, "DRAIN_DEADLINE_S", 0.3)  # it stays stuck to the end
    stuck = StuckBelowLoop()

    async def scenario() -> None:
        async with Runtime(CONFIG, plugins=host_with(("stuck", stuck))):
            await until(stuck.fed.is_set)

    with caplog.at_level(logging.INFO):
        on_a_real_time_loop(scenario)
    assert stuck.seen["stuck, first"] == (os.SCHED_FIFO, priority.BELOW_LOOP_PRIORITY)
    assert stuck.seen["stuck, last"] == (os.SCHED_OTHER, 0)
    assert "plugin stuck is stuck in abh3_feedback" in caplog.text


class StartRaises(AB):
    def start(self, feed: InputFeed) -> None:
        raise OSError(19, "No such device", "/dev/input/js0")


class StartBlocks(AB):
    def start(self, feed: InputFeed) -> None:
        RELEASE.wait()


@pytest.mark.parametrize(
    ("source", "why"),
    [
        (StartRaises, r"OSError\(19, .No such device.\)"),
        (StartBlocks, r"did not return within 0\.2 s"),
    ],
)
def test_a_source_whose_start_fails_or_blocks_fails_the_run_before_any_frame(
    monkeypatch: pytest.MonkeyPatch, source: type[AB], why: str
) -> None:
    monkeypatch.setattr(plugin_host, "START_DEADLINE_S", 0.2)

    class Provides:
        @hookimpl
        def abh3_input_sources(self, register: Any) -> None:
            register(source())

    good = Records()
    rt = Runtime(CONFIG, plugins=host_with(("good", good), ("dev", Provides())))

    async def scenario() -> None:
        async with rt:
            pytest.fail("the run must not start")

    with pytest.raises(PluginError, match=rf"plugin dev could not start \(input ab\): {why}"):
        asyncio.run(scenario())
    assert issubclass(PluginError, RunError)  # the CLI's exit 1
    assert good.stopped  # what started is closed again
    assert all(d.frames_received == 0 for d in rt.sims["b"].drives.values())


# ---------------------------------------------------------------- failure policy


def headless(config: Config, host: PluginHost, duration: float) -> int:
    return asyncio.run(
        run_headless(config, duration=duration, record=None, status_interval=0, plugins=host)
    )


def last_lines(caplog: pytest.LogCaptureFixture) -> str:
    return "\n".join(r.getMessage() for r in caplog.records)


def test_continue_disables_a_failing_plugin_names_it_at_the_end_and_exits_6(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config, host = configured("  bad: {}\n  good: {}\n", bad=Raises, good=Records)
    with caplog.at_level(logging.INFO):
        code = headless(config, host, 1.0)
    text = last_lines(caplog)
    assert code == 6, text
    assert host.failures["bad"] == MAX_FAILURES and "bad" in host.disabled
    assert "plugin bad was disabled during the run: 5 failure(s), the last in abh3_feedback" in text
    assert text.rstrip().endswith("plugin(s) disabled during the run: bad (exit code 6)")
    assert text.count("stop frame confirmed by the drive") == 2
    good = host.pm.get_plugin("good")
    assert isinstance(good, Records)
    assert good.stopped and good.rows > 0  # the others kept running


@pytest.mark.parametrize(
    "section",
    ["{on_error: stop}", "{critical: true}", "{on_error: continue, critical: true}"],
)
def test_stop_or_critical_ends_the_run_when_the_plugin_is_disabled(
    caplog: pytest.LogCaptureFixture, section: str
) -> None:
    config, host = configured(f"  bad: {section}\n  good: {{}}\n", bad=Raises, good=Records)
    with caplog.at_level(logging.INFO):
        start = time.monotonic()
        code = headless(config, host, 30.0)  # ended long before by the plugin
    text = last_lines(caplog)
    assert time.monotonic() - start < 10, text
    assert code == 1, text
    policy = "on_error: stop" if "stop" in section else "critical: true"
    failures = 1 if "stop" in section else MAX_FAILURES
    assert host.failures["bad"] == failures
    assert f"stopping: plugin bad was disabled ({failures} failure(s)" in text
    assert text.rstrip().endswith(f"; {policy}) (exit code 1)")
    assert "(exit code 6)" not in text and "(exit code 5)" not in text
    assert text.count("stop frame confirmed by the drive") == 2
    good = host.pm.get_plugin("good")
    assert isinstance(good, Records) and good.stopped


def test_an_exception_in_a_plugin_s_thread_is_that_plugin_s_failure(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config, host = configured(
        "  spins: {on_error: stop}\n  good: {}\n", spins=ThreadRaises, good=Records
    )
    hook = threading.excepthook
    with caplog.at_level(logging.INFO):
        code = headless(config, host, 30.0)
    text = last_lines(caplog)
    assert code == 1, text
    assert "plugin spins failed in its thread 'spinner' (failure 1 of 1): RuntimeError(" in text
    assert "stopping: plugin spins was disabled" in text
    assert threading.excepthook is hook  # put back at the end


def test_a_thread_a_plugin_starts_later_is_attributed_by_its_code(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config, host = configured("  late: {critical: true}\n", late=LaterThreadRaises)
    with caplog.at_level(logging.INFO):
        code = headless(config, host, 1.0)
    text = last_lines(caplog)
    assert "plugin late failed in its thread 'late' (failure 1 of 5): KeyError('late')" in text
    assert code == 0, text  # one failure of five: still running, not disabled


def test_critical_is_a_host_key_checked_like_on_error() -> None:
    with pytest.raises(Exception, match=r"plugins\.bad\.critical"):
        configured("  bad: {critical: maybe}\n", bad=Raises)
    _, host = configured("  bad: {critical: true}\n", bad=Raises)
    assert host.critical == {"bad"}


@pytest.mark.parametrize("value", ["0", "-1", "soon", "601"])
def test_start_timeout_is_a_host_key_checked_like_on_error(value: str) -> None:
    with pytest.raises(Exception, match=r"c\.yaml:\d+: plugins\.bad\.start_timeout_s"):
        configured(f"  bad: {{start_timeout_s: {value}}}\n", bad=Raises)


def test_start_timeout_gives_that_plugin_s_start_longer_and_no_other(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A slow board's DDS: ``start_timeout_s`` bounds the plugin's start hooks and its
    sources' starts instead of the 5 s every other plugin gets."""
    given: dict[str, float] = {}
    real = plugin_host.bounded

    def recorded(label: str, deadline: float, fn: Any) -> str | None:
        given[label] = deadline
        return real(label, deadline, fn)

    monkeypatch.setattr(plugin_host, "bounded", recorded)
    config, host = configured(
        "  dds: {start_timeout_s: 30}\n  good: {}\n", dds=ProvidesAB, good=Records
    )

    async def scenario() -> None:
        async with Runtime(config, plugins=host):
            pass

    asyncio.run(scenario())
    assert given == {
        "plugin dds abh3_start": 30.0,
        "plugin dds abh3_input_sources": 30.0,
        "input ab start": 30.0,
        "plugin good abh3_start": plugin_host.START_DEADLINE_S,
        "plugin good abh3_input_sources": plugin_host.START_DEADLINE_S,
        # the way out is not the start's: it keeps its own bound
        "input ab stop": plugin_host.STOP_DEADLINE_S,
        "plugin dds abh3_stop": plugin_host.STOP_DEADLINE_S,
        "plugin good abh3_stop": plugin_host.STOP_DEADLINE_S,
    }


FOREVER_PLUGIN = """
import threading
from abh3_supervisor.plugin_host.hookspecs import THREADS_BELOW_LOOP, hookimpl

class Forever:
    @hookimpl
    def abh3_start(self):
        # not a daemon (one started from the host's daemon threads is, unless told)
        threading.Thread(target=threading.Event().wait, name="forever", daemon=False).start()
"""
RUN_WITH_FOREVER = """
import sys
from importlib.metadata import EntryPoint
import abh3_supervisor.plugin_host.host as host
host.installed = lambda: {"forever": EntryPoint("forever", "foreverplugin:Forever", "abh3_supervisor")}
host.LEFTOVER_GRACE_S = 0.2
from abh3_supervisor.clients.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_thread_a_plugin_never_ends_cannot_hold_the_exit(tmp_path: Path) -> None:
    """The interpreter joins threads that are not daemons: without the host it would
    wait for this one forever, after the last lines."""
    (tmp_path / "foreverplugin.py").write_text(FOREVER_PLUGIN)
    (tmp_path / "run.py").write_text(RUN_WITH_FOREVER)
    (tmp_path / "c.yaml").write_text(
        TWO_UNITS.replace("channel: t", "channel: forever") + "plugins:\n  forever: {}\n"
    )
    run = subprocess.run(
        [sys.executable, str(tmp_path / "run.py"), "run", str(tmp_path / "c.yaml"),
         "--headless", "--no-socket", "--status-interval", "0", "--duration", "0.5"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"},
        timeout=30,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert run.stderr.count("stop frame confirmed by the drive") == 2
    assert (
        "exiting without waiting for thread 'forever' of plugin forever (exit code 0)" in run.stderr
    )


class StuckThenRaises:
    """Stuck past the run's end, then fails (on_error: stop would end the run)."""

    def __init__(self) -> None:
        self.go = threading.Event()

    @hookimpl
    def abh3_feedback(self) -> None:
        self.go.wait()
        raise ValueError("too late")


def test_a_plugin_left_behind_that_fails_after_the_run_disturbs_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(plugin_host, "DRAIN_DEADLINE_S", 0.2)
    uncaught: list[threading.ExceptHookArgs] = []
    monkeypatch.setattr(threading, "excepthook", uncaught.append)
    plugin = StuckThenRaises()
    host = host_with(("late", plugin))
    host.on_error["late"] = "stop"
    rt = Runtime(CONFIG, plugins=host)
    workers: list[threading.Thread] = []

    async def scenario() -> None:
        async with rt:
            await until(lambda: host.workers["late"].busy is not None)
            workers.append(host.workers["late"].thread)

    asyncio.run(scenario())  # the loop is closed from here on
    assert rt.stop_report == {"left": CONFIRMED, "right": CONFIRMED}
    plugin.go.set()
    workers[0].join(5)
    assert not workers[0].is_alive()
    assert host.failures == {"late": 1} and "late" in host.disabled
    assert uncaught == []  # its failure was handled, though nothing is left to stop


BAD_START_PLUGIN = """
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.plugin_host.hookspecs import THREADS_BELOW_LOOP, hookimpl

class Device(InputSource):
    def __init__(self):
        super().__init__("device", ("left",))

    def start(self, feed):
        raise OSError(19, "No such device", "/dev/input/js9")

    def stop(self):
        pass

class BadStart:
    @hookimpl
    def abh3_input_sources(self, register):
        register(Device())
"""
RUN_WITH_BAD_START = """
import sys
from importlib.metadata import EntryPoint
import abh3_supervisor.plugin_host.host as host
host.installed = lambda: {"dev": EntryPoint("dev", "badstart:BadStart", "abh3_supervisor")}
from abh3_supervisor.clients.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_abh3_run_exits_1_when_a_source_cannot_start_and_commands_nothing(
    tmp_path: Path,
) -> None:
    (tmp_path / "badstart.py").write_text(BAD_START_PLUGIN)
    (tmp_path / "run.py").write_text(RUN_WITH_BAD_START)
    (tmp_path / "c.yaml").write_text(
        TWO_UNITS.replace("channel: t", "channel: badstart") + "plugins:\n  dev: {}\n"
    )
    record = tmp_path / "r.log"
    run = subprocess.run(
        [sys.executable, str(tmp_path / "run.py"), "run", str(tmp_path / "c.yaml"),
         "--headless", "--no-socket", "--record", str(record)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"},
        timeout=30,
    )  # fmt: skip
    assert run.returncode == 1, run.stderr
    assert (
        "error: plugin dev could not start (input device): OSError(19, 'No such device')"
        in run.stderr
    )
    assert "Traceback" not in run.stderr
    assert commands_to(record, 1, Generation.G2021) == []  # not one command frame
    assert commands_to(record, 3, Generation.G2023) == []


class Retargets(AB):
    def __init__(self) -> None:
        InputSource.__init__(self, "retargets", ("left",), timeout=0.3)
        self.feed = None


@pytest.mark.parametrize("units", [("aaa",), "left", ("left", None), 7])
def test_retargeting_to_units_that_are_not_there_is_refused_and_leaves_nothing_moving(
    units: object,
) -> None:
    """Had the arbitration taken ('aaa',), left would be no source's unit any more and
    keep its 500 min⁻¹ for good (an unknown unit raised before left was decided)."""
    source = Retargets()

    class Provides:
        @hookimpl
        def abh3_input_sources(self, register: Any) -> None:
            register(source)

    rt = Runtime(CONFIG, plugins=host_with(("re", Provides())))
    notices: list[str] = []

    async def scenario() -> None:
        async with rt:
            sup = rt.supervisor
            sup.subscribe(lambda e: notices.append(e.message) if isinstance(e, Notice) else None)
            for text in ("SERVO ON ON", "START ON ON"):
                assert await sup.command("left", text) == ""
            assert source.feed is not None
            source.feed.velocity(500.0, 0.0)
            left = drives(rt)["left"]
            await until(lambda: left.cmd_raw != (0, 0))
            source.feed.retarget(units)  # type: ignore[arg-type]
            await until(lambda: left.cmd_raw == (0, 0))  # its timeout, as silence
            assert sup.units["left"].setpoint.ay == 0.0

    asyncio.run(scenario())
    assert any(n.startswith("input retargets refused: retarget(") for n in notices), notices
