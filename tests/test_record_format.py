"""``--record`` with a name no format is known for is a mistake on the command line:
exit 2, the known extensions listed, before anything opens — in `abh3 run` (headless and
on a terminal) and `abh3 commission`, by one check (runtime/recorder.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.runtime.recorder import check_format
from tests.support.terminal import on_a_terminal

ROOT = Path(__file__).resolve().parent.parent
KNOWN = ".log .asc .blf .csv .mcap, or python-can's .db .mf4 .trc .txt (text ones also .gz)"


def refused(out: str, record: Path) -> None:
    assert "Traceback" not in out
    assert f"error: --record {record}: '.unknownext' is not a recording format; use {KNOWN}" in out
    assert "recording all bus traffic" not in out and "online" not in out  # nothing opened
    assert not record.exists()


@pytest.mark.wallclock
def test_headless_run_refuses_it_before_anything_opens(tmp_path: Path) -> None:
    record = tmp_path / "x.unknownext"
    cmd = [sys.executable, "-m", "abh3_supervisor", "run", "configs/demo.yaml", "--headless"]
    out = subprocess.run(
        [*cmd, "--record", str(record), "--duration", "1"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert out.returncode == 2, out.stderr
    refused(out.stderr, record)


@pytest.mark.wallclock
def test_run_on_a_terminal_refuses_it_before_the_supervisor_starts(tmp_path: Path) -> None:
    record = tmp_path / "x.unknownext"
    code, screen = on_a_terminal(["run", "configs/demo.yaml", "--record", str(record)])
    text = screen.decode(errors="replace").replace("\r\n", "\n")
    assert code == 2, text
    assert "starting the supervisor" not in text
    refused(text, record)


@pytest.mark.wallclock
def test_commission_refuses_it_before_anything_opens(tmp_path: Path) -> None:
    record = tmp_path / "x.unknownext"
    cmd = [sys.executable, "-m", "abh3_supervisor", "commission", "configs/demo.yaml"]
    out = subprocess.run(
        [*cmd, "--record", str(record), "--yes", "--wheels-off-ground"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert out.returncode == 2, out.stdout + out.stderr
    refused(out.stdout + out.stderr, record)


@pytest.mark.parametrize(
    "name", ["r.log", "R.MCAP", "r.asc", "r.blf", "r.csv", "r.trc", "r.db", "r.log.gz"]
)
def test_every_format_that_can_be_written_passes(name: str) -> None:
    check_format(Path(name))


@pytest.mark.parametrize("name", ["r", "r.gz", "r.blf.gz", "r.mcapp", "r.log.zip"])
def test_what_cannot_be_written_is_refused(name: str) -> None:
    with pytest.raises(Abh3Error, match="is not a recording format"):
        check_format(Path(name))


def test_a_recording_in_a_folder_that_does_not_exist_is_refused_before_anything_opens(
    tmp_path: Path,
) -> None:
    with pytest.raises(Abh3Error, match=r"cannot write: there is no folder "):
        check_format(tmp_path / "missing" / "run.log")
    check_format(tmp_path / "run.log")  # a folder that exists: accepted
