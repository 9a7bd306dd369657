"""A full disk under the CSV plugin: whole rows only, and an error naming the file."""

from __future__ import annotations

import asyncio
import csv
import errno
import logging
from pathlib import Path
from typing import Any

import pytest

from abh3_plugins.csv_output import COLUMNS, _File
from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.headless import run_headless
from tests.support.disk import FillsUp
from tests.support.rig import TWO_UNITS


def row(i: int) -> dict[str, Any]:
    return {c: i for c in COLUMNS}


def test_a_full_disk_leaves_whole_rows_and_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    f = _File(path, 0, 0)
    for i in range(10):
        f.write(row(i))
    f.flush()
    f.handle = FillsUp(f.handle, room=150)  # type: ignore[assignment]
    for i in range(10, 20):
        f.write(row(i))
    with pytest.raises(OSError, match=r"No space left on device: '.*out\.csv'"):
        f.flush()
    text = path.read_text(encoding="utf-8")
    assert text.endswith("\n")  # cut back to the last whole row
    rows = list(csv.DictReader(text.splitlines()))
    assert [r["unit"] for r in rows] == [str(i) for i in range(10)]


@pytest.mark.wallclock
@pytest.mark.parametrize(("policy", "code"), [("stop", 1), ("continue", 5)])
def test_on_error_decides_whether_the_run_goes_on(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    policy: str,
    code: int,
) -> None:
    real_flush = _File.flush
    calls = {"n": 0}

    def flush(self: _File) -> None:  # the header goes out, then the disk is full
        calls["n"] += 1
        if calls["n"] > 1:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.name))
        real_flush(self)

    monkeypatch.setattr(_File, "flush", flush)
    path = tmp_path / "out.csv"
    text = TWO_UNITS + f"plugins:\n  csv: {{path: '{path}', flush_s: 0.1, on_error: {policy}}}\n"
    config = parse_config(text, "c.yaml")
    host = PluginHost(config)
    with caplog.at_level(logging.INFO):
        result = asyncio.run(
            run_headless(config, duration=1.5, record=None, status_interval=0, plugins=host)
        )
    assert result == code
    assert caplog.text.count("plugin csv: output failed: [Errno 28] No space left") == 1
    assert "Traceback" not in caplog.text
    assert caplog.text.count("stop frame confirmed by the drive") == 2
    stopping = "stopping: the output of plugin csv failed (on_error: stop)" in caplog.text
    assert stopping == (policy == "stop")


def test_on_error_is_checked_like_any_key() -> None:
    text = TWO_UNITS + "plugins:\n  csv: {path: out.csv, on_error: ignore}\n"
    with pytest.raises(ConfigError, match=r"plugins\.csv\.on_error: 'ignore' is not one of"):
        PluginHost(parse_config(text, "c.yaml"))
