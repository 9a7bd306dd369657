"""docs/plugins.md's worked examples, exactly as written: the output, the input source and
the safety watchdog, declared by the guide's pyproject and run by its YAML on the
simulator."""

from __future__ import annotations

import asyncio
import json
import logging
import re
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.plugin_host.host import GROUP, PluginHost
from abh3_supervisor.runtime.headless import run_headless

GUIDE = Path(__file__).resolve().parent.parent / "docs" / "plugins.md"
BLOCK = re.compile(r"^```\w+\n# file: (\S+)\n(.*?)^```$", re.M | re.S)


def examples() -> dict[str, str]:
    """Every code block of the guide that names its file, by that name."""
    return {name: text for name, text in BLOCK.findall(GUIDE.read_text(encoding="utf-8"))}


def test_the_guide_has_the_three_worked_examples_and_declares_each() -> None:
    files = examples()
    assert {"abh3_jsonl.py", "abh3_script.py", "abh3_overspeed.py", "example.yaml"} <= set(files)
    project = tomllib.loads(files["pyproject.toml"])
    points = project["project"]["entry-points"]["abh3_supervisor"]
    assert set(points) == {"jsonl", "script", "overspeed"}
    modules = {p.split(":")[0] + ".py" for p in points.values()}
    assert modules <= set(files)
    for name, text in files.items():
        if name.endswith(".py"):  # the public API only
            imports = re.findall(r"^from (abh3_supervisor[\w.]*) import", text, re.M)
            assert imports == ["abh3_supervisor.plugin_api"], name


@pytest.mark.wallclock
def test_the_worked_examples_run_on_the_simulator(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    files = examples()
    for name, text in files.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)  # run.jsonl lands here
    points = tomllib.loads(files["pyproject.toml"])["project"]["entry-points"][GROUP]
    available = {name: EntryPoint(name, value, GROUP) for name, value in points.items()}
    yaml = files["example.yaml"].replace("channel: docs", "channel: docs-examples")
    config = parse_config(yaml, str(tmp_path / "example.yaml"))
    host = PluginHost(config, available=available)
    with caplog.at_level(logging.INFO):
        code = asyncio.run(
            run_headless(config, duration=30.0, record=None, status_interval=0, plugins=host)
        )
    assert code == 0  # the script ended the run: a normal stop
    assert "plugin script ends the run: script done after 3 s" in caplog.text
    assert re.search(
        r"EMERGENCY STOP \(plugin overspeed: unit left at \d+ min-1, over 200\)", caplog.text
    )
    records = [json.loads(line) for line in (tmp_path / "run.jsonl").read_text().splitlines()]
    estop = next(i for i, r in enumerate(records) if "estop" in r)
    assert records[estop]["estop"] is True
    assert records[estop]["by"].startswith("plugin overspeed: unit left at")
    before = [r for r in records[:estop] if "vel_a" in r]
    after = [r for r in records[estop:] if "vel_a" in r]
    assert any(r["owner"] == "script" and r["cmd"][0] > 0 for r in before)
    assert max(abs(r["vel_a"]) for r in before) > 200  # what tripped it
    assert after and all(r["cmd"] == [0.0, 0.0] for r in after)  # nothing moved it again
    assert abs(after[-1]["vel_a"]) < 1.0  # stopped
    assert any("word" in r for r in records)  # flag changes, named
