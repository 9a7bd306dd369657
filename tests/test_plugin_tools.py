"""The plugin authors' tools: `abh3 plugins` and `abh3 plugin new` (the template passes
its own test, installed by pip)."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import types
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from abh3_supervisor.clients import plugins as listing_cli
from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.plugin_template import new_plugin
from abh3_supervisor.plugin_host import inventory
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import installed
from tests.support.rig import TWO_UNITS

ROOT = Path(__file__).resolve().parent.parent
GROUP = "abh3_supervisor"


# ---------------------------------------------------------------- abh3 plugins


class Declares:
    ABH3_API_VERSION = "2.1"

    @hookimpl
    def abh3_feedback(self) -> None:
        pass

    @hookimpl
    def abh3_stop(self) -> None:
        pass

    @hookimpl
    def abh3_feedbak(self) -> None:
        pass


def fake_installed(monkeypatch: pytest.MonkeyPatch, extra: dict[str, str]) -> None:
    eps = dict(installed())
    for name, value in extra.items():
        eps[name] = EntryPoint(name=name, value=value, group=GROUP)
    monkeypatch.setattr(listing_cli, "installed", lambda: eps)


def test_listing_says_version_api_hooks_and_what_the_config_enables(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    fake_installed(
        monkeypatch,
        {"declares": f"{__name__}:Declares", "broken": "abh3_no_such_module_here:Plugin"},
    )
    monkeypatch.setattr(listing_cli, "api_version", lambda: "1.4")
    config = tmp_path / "c.yaml"
    config.write_text(TWO_UNITS + "plugins:\n  csv: {path: x.csv}\n  gone: {}\n")
    rows = {r["name"]: r for r in listing_cli.listing(config)["plugins"]}
    csv = rows["csv"]
    assert csv["distribution"] == "abh3-supervisor" and csv["version"]
    assert {"abh3_configure", "abh3_feedback", "abh3_stop"} <= set(csv["hooks"])
    assert csv["enabled"] is True and rows["keyboard"]["enabled"] is False
    declares = rows["declares"]
    assert declares["api_version"] == "2.1" and declares["compatible"] is False
    assert declares["hooks"] == ["abh3_feedback", "abh3_stop"]  # the typo is no hook:
    (problem,) = declares["problems"]
    assert "abh3_feedbak (" in problem and "did you mean 'abh3_feedback'?" in problem
    assert csv["problems"] == []
    assert (
        rows["broken"]["error"] == "ModuleNotFoundError: No module named 'abh3_no_such_module_here'"
    )
    assert rows["broken"]["hooks"] == []
    assert rows["gone"]["error"] == "not installed" and rows["gone"]["enabled"] is True


def test_the_text_listing_names_the_failure_in_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    fake_installed(monkeypatch, {"broken": "abh3_no_such_module_here:Plugin"})
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "broken\n  failed to load: ModuleNotFoundError: No module named" in out
    assert "Traceback" not in out
    assert "hooks: abh3_config_schema, abh3_configure, " in out  # the built-ins'
    assert "API version: 1.0 (compatible with 1.3)" in out  # the built-ins declare it


def test_the_declared_api_version_is_read_from_the_object_or_its_module() -> None:
    module = types.ModuleType("m")
    module.ABH3_API_VERSION = "1.0"  # type: ignore[attr-defined]
    assert inventory.declared_api(module) == "1.0"
    assert inventory.declared_api(Declares()) == "2.1"
    assert inventory.declared_api(object()) is None
    assert inventory.compatible("1.3", "1.0") is True
    assert inventory.compatible("2.0", "1.9") is False
    assert inventory.compatible(None, "1.0") is None


def test_the_run_log_line_names_each_plugin_and_its_version() -> None:
    line = inventory.loaded_line(["csv", "mine"], installed())
    assert line.startswith("plugins loaded: csv (abh3-supervisor ")
    assert line.endswith(", mine (registered in-process)")
    assert inventory.loaded_line([], {}) == "plugins loaded: none"


@pytest.mark.wallclock
def test_abh3_plugins_json_in_a_process_of_its_own() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "plugins", "configs/demo.yaml", "--json"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert data["config"] == "configs/demo.yaml"
    assert {"csv", "keyboard", "joystick", "ros2"} <= {r["name"] for r in data["plugins"]}


# ---------------------------------------------------------------- abh3 plugin new


def load(path: Path, name: str) -> types.ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.wallclock  # its test runs the plugin for a second
def test_the_template_passes_its_own_test(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    package = new_plugin("speed_log", tmp_path)
    assert package == tmp_path / "abh3-speed-log"
    monkeypatch.syspath_prepend(str(package))
    monkeypatch.delitem(sys.modules, "abh3_speed_log", raising=False)
    test = load(package / "tests" / "test_abh3_speed_log.py", "generated_test")
    test.test_it_hears_every_unit_and_the_run_ends_cleanly()
    plugin = sys.modules["abh3_speed_log"]
    assert plugin.ABH3_API_VERSION == sys.modules["abh3_supervisor.plugin_api"].API_VERSION


def test_the_template_refuses_a_bad_name_or_an_existing_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["plugin", "new", "Speed-Log", "--dir", str(tmp_path)]) == 2
    assert main(["plugin", "new", "speed_log", "--dir", str(tmp_path)]) == 0
    assert main(["plugin", "new", "speed_log", "--dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "'Speed-Log' cannot name a plugin" in err and "exists already" in err
    assert "did you mean 'speed_log'?" in err
    assert "Traceback" not in err


@pytest.mark.wallclock
def test_the_template_installs_with_pip_is_listed_and_passes_its_test(tmp_path: Path) -> None:
    package = new_plugin("speed_log", tmp_path)
    site = tmp_path / "site"
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
            str(site),
            str(package),
        ],
        capture_output=True,
        text=True,
    )
    assert pip.returncode == 0, pip.stderr
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    listed = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "plugins", "--json"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    assert listed.returncode == 0, listed.stderr
    row = next(r for r in json.loads(listed.stdout)["plugins"] if r["name"] == "speed_log")
    assert (row["distribution"], row["version"]) == ("abh3-speed-log", "0.1.0")
    assert row["compatible"] is True and row["hooks"] == ["abh3_feedback", "abh3_stop"]
    tested = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"],
        capture_output=True,
        text=True,
        env=env,
        cwd=package,
    )
    assert tested.returncode == 0, tested.stdout + tested.stderr
    assert "1 passed" in tested.stdout
