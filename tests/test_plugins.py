"""The plugin host: discovery, configuration errors, isolation, off-bus-path dispatch."""

from __future__ import annotations

import asyncio
import csv
import inspect
import json
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.state import Feedback
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_host import hookspecs
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import MAX_FAILURES, PluginHost, installed
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.support.rig import TWO_UNITS, present, set_velocity

ROOT = Path(__file__).resolve().parent.parent


def with_plugins(text: str) -> str:
    return TWO_UNITS + "plugins:\n" + text


def test_builtins_are_registered_through_the_entry_point_group() -> None:
    assert {"csv", "keyboard", "joystick"} <= set(installed())


def test_naming_a_plugin_that_is_not_installed_lists_the_installed_ones() -> None:
    cfg = parse_config(with_plugins("  cvs: {}\n"), "p.yaml")
    with pytest.raises(ConfigError) as info:
        PluginHost(cfg)
    assert re.search(
        r"p\.yaml:\d+: plugins\.cvs: no plugin named 'cvs' is installed; did you mean "
        r"'csv'\? \(installed: .*csv.*joystick.*keyboard",
        info.value.problems[0],
    )


def test_plugin_sections_are_validated_with_file_line_and_key() -> None:
    cfg = parse_config(
        with_plugins(
            "  csv:\n    path: x.csv\n    flush: 2\n  joystick: {units: [left], gainX: fast}\n"
        ),
        "p.yaml",
    )
    with pytest.raises(ConfigError) as info:
        PluginHost(cfg)
    problems = "\n".join(info.value.problems)
    assert "p.yaml:11: plugins.csv.flush: unknown key; did you mean 'flush_s'?" in problems
    assert "plugins.joystick.gainX: expected a number" in problems


@pytest.mark.wallclock
def test_check_reports_plugin_errors_with_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(with_plugins("  keyboard: {speed: 3}\n"))
    out = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "check", str(bad)],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert out.returncode == 2
    assert "plugins.keyboard.units: missing" in out.stderr and "Traceback" not in out.stderr


class Broken:
    """Starts, then raises in every hook."""

    calls = 0

    def _boom(self) -> None:
        Broken.calls += 1
        raise RuntimeError("plugin bug")

    @hookimpl
    def abh3_feedback(self) -> None:
        self._boom()

    @hookimpl
    def abh3_status(self) -> None:
        self._boom()

    @hookimpl
    def abh3_stop(self) -> None:
        self._boom()


class Recorder:
    def __init__(self, enough: int) -> None:
        self.feedback: list[tuple[str, Feedback]] = []
        self.enough = enough
        self.enough_seen = threading.Event()
        self.started = False
        self.stopped = False

    async def done(self) -> None:
        assert await asyncio.to_thread(self.enough_seen.wait, 10)

    @hookimpl
    def abh3_start(self) -> None:
        self.started = True

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback) -> None:
        self.feedback.append((unit, feedback))
        if len(self.feedback) == self.enough:
            self.enough_seen.set()

    @hookimpl
    def abh3_stop(self) -> None:
        self.stopped = True


@pytest.mark.wallclock
def test_a_plugin_raising_in_every_hook_does_not_stop_the_others() -> None:
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    host.register(Broken(), "broken")
    good = Recorder(enough=100)
    host.register(good, "good")

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host):
            await good.done()
            assert "broken" not in host.names  # disabled after repeated failures

    asyncio.run(scenario())
    assert Broken.calls == MAX_FAILURES + 1  # and abh3_stop, to close what it opened
    assert good.stopped and len(good.feedback) >= 100


class Slow:
    @hookimpl
    def abh3_feedback(self) -> None:
        time.sleep(0.2)  # a slow output: must not hold up the bus


@pytest.mark.wallclock
def test_a_slow_plugin_never_delays_the_scheduler() -> None:
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    host.register(Slow(), "slow")
    good = Recorder(enough=100)  # 100 replies = 1 s of two units at 50 Hz
    host.register(good, "good")

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host) as rt:
            await good.done()
            stats = rt.supervisor.schedulers["b"].slots["left"].stats
            assert stats.commands_sent >= 45  # ~50 in the second the slow plugin took ~10 events

    start = time.monotonic()
    asyncio.run(scenario())
    assert time.monotonic() - start < 9  # the slow queue is abandoned after its timeout


def test_every_hook_is_documented() -> None:
    guide = (ROOT / "docs" / "plugins.md").read_text(encoding="utf-8")
    hooks = [
        n for n, f in inspect.getmembers(hookspecs, inspect.isfunction) if n.startswith("abh3_")
    ]
    assert len(hooks) == 14
    for name in hooks:
        assert f"### `{name}`" in guide, f"{name} is not documented in docs/plugins.md"


def run_csv(tmp_path: Path, plugin_yaml: str, seconds: float = 1.0) -> Any:
    cfg = parse_config(with_plugins(plugin_yaml), "c.yaml")
    host = PluginHost(cfg)

    async def scenario() -> Any:
        async with Runtime(cfg, plugins=host) as rt:
            sup = rt.supervisor
            for unit in ("left", "right"):
                sup.apply_text(unit, "SERVO ON ON")
                sup.apply_text(unit, "START ON ON")
            set_velocity(sup, "left", 100.0, 10.0, source=present(sup, "left"))
            await asyncio.sleep(seconds)  # let it run: what is recorded is the subject here
            return rt.sims["b"]

    return asyncio.run(scenario())


@pytest.mark.wallclock
def test_csv_rows_match_what_the_drives_report(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    sim = run_csv(tmp_path, f"  csv: {{path: '{path}'}}\n")
    text = path.read_text()
    assert text.splitlines()[0].startswith("time [s],note,unit,kind,cmd_ay [min-1 or %],")
    assert "vel_a [min-1]" in text.splitlines()[0] and "main_volt [V]" in text.splitlines()[0]
    assert "-0.0," not in text  # rounded to what the frames carry, never a negative zero
    rows = [{k.split(" ")[0]: v for k, v in r.items()} for r in csv.DictReader(path.open())]
    left = [r for r in rows if r["unit"] == "left"]
    assert {r["unit"] for r in rows} == {"left", "right"}
    steady = [r for r in left if r["cmd_ay"] == "100.0" and r["vel_y"] == "100.0"]
    assert steady and steady[-1]["vel_x"] == "10.0" and steady[-1]["load_a"].isdigit()
    assert steady[-1]["error"] == "0x00000000" and "TRAVEL_MODEL" in steady[-1]["control_names"]
    assert float(steady[-1]["main_volt"]) < 23.7 and steady[-1]["pulse_a"]
    assert "AY_START" in steady[-1]["inputs_names"]  # the commanded input word
    assert all(r["inputs"].startswith("0x") for r in rows)
    right = [r for r in rows if r["unit"] == "right"]
    assert right[-2]["drive_inputs"].startswith("0x")  # 2023: the word the drive sees
    for unit in (left, right):  # a last row after the stop, showing it
        last = unit[-1]
        assert last["note"] == "after the stop" and all(not r["note"] for r in unit[:-1])
        assert (last["cmd_ay"], last["cmd_bx"]) == ("0.0", "0.0")
        assert "SERVO" not in last["inputs_names"]  # the safe word
    assert "SERVO" not in right[-1]["control_names"]  # 2023: in the reply to the stop
    drive = sim.drives[1]
    assert int(steady[-1]["pulse_a"]) <= drive.pulses[0]


@pytest.mark.wallclock
def test_csv_per_unit_files_and_rotation(tmp_path: Path) -> None:
    run_csv(tmp_path, f"  csv: {{path: '{tmp_path}/{{unit}}.csv', rotate_bytes: 4000}}\n", 0.5)
    left = sorted(tmp_path.glob("left-*.csv"))
    assert len(left) >= 2 and sorted(tmp_path.glob("right-*.csv"))
    for part in left:
        rows = list(csv.DictReader(part.open()))
        assert rows and all(r["unit"] == "left" for r in rows)


@pytest.mark.wallclock
def test_csv_file_is_complete_after_sigterm(tmp_path: Path) -> None:
    path = tmp_path / "sig.csv"
    cfg = tmp_path / "c.yaml"
    demo = (ROOT / "configs" / "demo.yaml").read_text()
    cfg.write_text(demo + f"\nplugins:\n  csv: {{path: '{path}'}}\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless"],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stderr is not None
    for line in proc.stderr:
        if "demo/right" in line:  # the first status line: a second of rows is written
            break
    proc.terminate()
    rest = proc.stderr.read()
    assert proc.wait(30) == 0, rest
    rows = [{k.split(" ")[0]: v for k, v in r.items()} for r in csv.DictReader(path.open())]
    assert len(rows) >= 80
    for unit in ("left", "right"):
        last = [r for r in rows if r["unit"] == unit][-1]
        assert (last["cmd_ay"], last["cmd_bx"]) == ("0.0", "0.0")  # the stop is recorded
        assert last["note"] == "after the stop"


@pytest.mark.wallclock
def test_example_third_party_plugin_installs_and_is_picked_up(tmp_path: Path) -> None:
    target = tmp_path / "site"
    pip = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(ROOT / "docs" / "examples" / "abh3-example-plugin"),
        ],
        capture_output=True,
        text=True,
    )
    assert pip.returncode == 0, pip.stderr
    out_json = tmp_path / "speeds.json"
    cfg = tmp_path / "c.yaml"
    cfg.write_text(
        (ROOT / "configs" / "demo.yaml").read_text()
        + f"\nplugins:\n  speed_summary: {{path: '{out_json}'}}\n"
    )
    env = {"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"}
    run = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless", "--duration", "1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
    )
    assert run.returncode == 0, run.stderr
    summary = json.loads(out_json.read_text())
    assert summary["left"]["samples"] > 20 and summary["left"]["peak_min-1"] > 100
