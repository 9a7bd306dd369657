"""The plugin authors' harness (abh3_supervisor.plugin_testing): a YAML on the simulator
with a plugin built by the test, its records, the wire, the exit code `abh3 run` gives."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from abh3_supervisor import plugin_testing
from abh3_supervisor.config.source import Section
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_testing import (
    PluginRun,
    run_with_plugin,
    running,
)
from abh3_supervisor.protocol.ids import dp0_command_id

pytestmark = pytest.mark.wallclock  # a run takes its seconds of real time

# a file meant for a robot on can0: the harness runs it on the simulator as written
CONFIG = """
buses:
  b: {interface: socketcan, channel: can0}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50}
"""
LEFT_DP0 = dp0_command_id(1, 2)
# the fixture (a plugin's conftest.py loads it as `abh3_run` with pytest_plugins)
harness_fixture = plugin_testing.abh3_run


class Counts:
    def __init__(self) -> None:
        self.feedback = 0
        self.stopped = False

    @hookimpl
    def abh3_feedback(self, unit: str) -> None:
        self.feedback += 1

    @hookimpl
    def abh3_stop(self) -> None:
        self.stopped = True


def test_an_output_plugin_hears_what_the_run_records_and_the_wire_is_seen() -> None:
    plugin = Counts()
    run = run_with_plugin(CONFIG, plugin, "counts", seconds=1.0)
    assert run.exit_code == 0 and run.error is None, run.log
    assert plugin.stopped and plugin.feedback == len(run.feedback) >= 30
    assert {unit for unit, _, _ in run.feedback} == {"left"}
    assert ("left", True) in [(u, online) for u, online, _ in run.health]
    commands = run.frames_of(LEFT_DP0, mask=0x3FFFFFF)
    assert 40 <= len(commands) <= 60  # 50 Hz for a second, the stop frame at the end
    assert all(0 <= f.t < 2 for f in commands)
    assert any("plugins loaded: counts (registered in-process)" in line for line in run.log)


class Forward(InputSource):
    """Commands 100 min⁻¹ on A from a thread of its own, as a plugin's source would."""

    def __init__(self) -> None:
        super().__init__("forward", ("left",), timeout=0.5)
        self.done = threading.Event()

    def start(self, feed: InputFeed) -> None:
        def stream() -> None:
            while not self.done.is_set():
                feed.velocity(100.0, 0.0)
                self.done.wait(0.05)

        threading.Thread(target=stream, daemon=True).start()

    def stop(self) -> None:
        self.done.set()


class Provides:
    @hookimpl
    def abh3_input_sources(self, register: Any) -> None:
        register(Forward())


def test_an_input_plugins_commands_are_in_the_records_and_stop_at_the_end() -> None:
    run = run_with_plugin(CONFIG, Provides(), "forward", seconds=1.0)
    assert run.exit_code == 0, run.log
    assert run.sources == ["forward"]
    assert any(sp.ay == 100.0 for _, _, sp in run.feedback)
    last = run.frames_of(LEFT_DP0, mask=0x3FFFFFF)[-1]
    assert last.data[:4] == bytes(4)  # the stop: zero on both axes


def test_running_yields_while_it_runs_so_a_test_waits_for_a_condition() -> None:
    with running(CONFIG, Counts(), "counts", seconds=2.0) as run:
        assert run.wait_for(lambda r: len(r.feedback) >= 10, timeout=10)
        assert run.exit_code is None  # still running: it ends at its 2 s
    assert run.exit_code == 0


class Configured:
    def __init__(self) -> None:
        self.gain = 0.0

    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        section.only({"gain"})
        self.gain = section.number("gain", 1.0, 0.0, 10.0)


def test_settings_reach_the_plugin_and_mistakes_are_exit_2_with_file_line() -> None:
    plugin = Configured()
    assert run_with_plugin(CONFIG, plugin, "c", 0.2, settings={"gain": 2.5}).exit_code == 0
    assert plugin.gain == 2.5
    bad = run_with_plugin(CONFIG + "plugins:\n  c: {gane: 2}\n", Configured(), "c", 0.2)
    assert bad.exit_code == 2 and bad.error is not None
    assert "<test config>:7: plugins.c.gane: unknown key; did you mean 'gain'?" in bad.error


def test_a_broken_file_is_exit_2_with_its_problems() -> None:
    run = run_with_plugin(CONFIG + "  - {name: left, abh3_id: 9}\n", Counts(), "c", 0.2)
    assert run.exit_code == 2 and run.error is not None and "<test config>:" in run.error
    assert not run.frames


class Typo:
    @hookimpl
    def abh3_feedbak(self) -> None:
        pass


def test_a_typod_hook_fails_the_run_as_check_does() -> None:
    run = run_with_plugin(CONFIG, Typo(), "typo", 0.2)
    assert run.exit_code == 2 and run.error is not None
    assert "did you mean 'abh3_feedback'?" in run.error and not run.frames


class CannotStart:
    @hookimpl
    def abh3_start(self) -> None:
        raise RuntimeError("no device")


def test_a_plugin_that_cannot_start_is_exit_1_before_any_frame() -> None:
    run = run_with_plugin(CONFIG, CannotStart(), "dead", 0.2)
    assert run.exit_code == 1 and run.error is not None
    assert "plugin dead could not start (abh3_start)" in run.error
    assert not run.frames_of(LEFT_DP0, mask=0x3FFFFFF)


def test_the_fixture_is_run_with_plugin(harness_fixture: Any) -> None:
    run: PluginRun = harness_fixture(CONFIG, Counts(), "counts", 0.3)
    assert run.exit_code == 0 and run.feedback
