"""`check` and `run` refuse what pluggy accepts silently: a typo'd hook, a hook method
without @hookimpl, settings for a plugin that reads none (plugin_host/validate.py)."""

from __future__ import annotations

import re
import subprocess
import sys
from importlib.metadata import EntryPoint
from pathlib import Path
from typing import Any, cast

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.source import Section
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.plugin_host.host import PluginHost, installed
from tests.support.rig import TWO_UNITS

ROOT = Path(__file__).resolve().parent.parent


class Given:
    """An entry point that loads an object built here (the plugin under test)."""

    def __init__(self, plugin: object) -> None:
        self.plugin = plugin

    def load(self) -> object:
        return self.plugin


def problems(plugin: object, section: str = "{}") -> list[str]:
    cfg = parse_config(TWO_UNITS + f"plugins:\n  mine: {section}\n", "p.yaml")
    available = {**installed(), "mine": cast(EntryPoint, Given(plugin))}
    try:
        PluginHost(cfg, available)
    except ConfigError as exc:
        return exc.problems
    return []


class Typo:
    @hookimpl
    def abh3_feedbak(self, unit: str) -> None:
        pass


class Unmarked:
    def abh3_feedback(self, unit: str) -> None:
        pass


class MarkedWrongName:
    @hookimpl
    def feedback(self, unit: str) -> None:
        pass


class NoConfigure:
    @hookimpl
    def abh3_feedback(self, unit: str) -> None:
        pass


class Configures:
    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        section.only({"path"})

    @hookimpl(specname="abh3_stop")
    def close(self) -> None:
        pass

    def helper(self) -> None:  # an ordinary method: none of the host's business
        pass


def test_a_typod_hook_names_file_line_and_the_closest_hook() -> None:
    (problem,) = problems(Typo())
    assert re.fullmatch(
        r"p\.yaml:\d+: plugins\.mine: plugin 'mine': abh3_feedbak \(.*test_plugin_validate\.py:\d+\) "
        r"matches no hook; did you mean 'abh3_feedback'\?",
        problem,
    ), problem


def test_a_hook_method_without_hookimpl_is_refused() -> None:
    (problem,) = problems(Unmarked())
    assert "plugin 'mine': abh3_feedback (" in problem
    assert "has no @hookimpl, so it is never called" in problem


def test_a_marked_method_named_like_no_hook_is_refused() -> None:
    (problem,) = problems(MarkedWrongName())
    assert "feedback (" in problem and "matches no hook; did you mean 'abh3_feedback'?" in problem


def test_settings_for_a_plugin_without_configure_are_refused_but_the_host_keys_are_not() -> None:
    (problem,) = problems(NoConfigure(), "{path: x.csv, on_error: stop}")
    assert re.fullmatch(
        r"p\.yaml:\d+: plugins\.mine\.path: plugin 'mine' takes no settings "
        r"\(it implements no abh3_configure\)",
        problem,
    ), problem
    assert problems(NoConfigure(), "{on_error: stop}") == []
    assert problems(NoConfigure(), "{critical: true}") == []


def test_a_correct_plugin_with_specname_and_helpers_passes() -> None:
    assert problems(Configures(), "{path: x.csv}") == []


@pytest.mark.parametrize("name", ["csv", "keyboard", "joystick", "ros2"])
def test_the_builtin_plugins_pass(name: str) -> None:
    plugin: Any = installed()[name].load()
    obj = plugin() if isinstance(plugin, type) else plugin
    assert not [p for p in problems(obj) if "matches no hook" in p or "@hookimpl" in p]


def test_the_documented_example_plugin_passes(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(ROOT / "docs" / "examples" / "abh3-example-plugin"))
    from abh3_speed_summary import SpeedSummary  # type: ignore[import-not-found]

    assert problems(SpeedSummary(), "{path: s.json}") == []


PACKAGE = {
    "pyproject.toml": """\
[build-system]
requires = ["setuptools>=68"]
build-backend = "setuptools.build_meta"

[project]
name = "abh3-typo"
version = "0.2.0"

[project.entry-points.abh3_supervisor]
typo = "abh3_typo:Typo"

[tool.setuptools]
py-modules = ["abh3_typo"]
""",
    "abh3_typo.py": """\
from abh3_supervisor.plugin_host.hookspecs import hookimpl


class Typo:
    @hookimpl
    def abh3_feedbak(self, unit):
        pass

    def abh3_stop(self):
        pass
""",
}


@pytest.mark.wallclock
def test_an_installed_plugin_with_hook_mistakes_fails_check_and_run_with_exit_2(
    tmp_path: Path,
) -> None:
    source = tmp_path / "pkg"
    source.mkdir()
    for name, text in PACKAGE.items():
        (source / name).write_text(text)
    site = tmp_path / "site"
    pip = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(site),
            str(source),
        ],
        capture_output=True,
        text=True,
    )
    assert pip.returncode == 0, pip.stderr
    config = tmp_path / "c.yaml"
    config.write_text(TWO_UNITS + "plugins:\n  typo: {}\n")
    env = {"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"}
    for command in (["check"], ["run", "--headless", "--no-socket", "--duration", "1"]):
        out = subprocess.run(
            [sys.executable, "-m", "abh3_supervisor", command[0], str(config), *command[1:]],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
        )
        assert out.returncode == 2, out.stderr
        assert f"{config}:9: plugins.typo: plugin 'typo': abh3_feedbak (" in out.stderr
        assert "abh3_typo.py:6) matches no hook; did you mean 'abh3_feedback'?" in out.stderr
        assert "abh3_stop (" in out.stderr and "has no @hookimpl" in out.stderr
        assert "Traceback" not in out.stderr
