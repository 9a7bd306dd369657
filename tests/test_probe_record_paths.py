"""Probe (issue 29): ``--record`` naming the file the ``csv`` plugin writes.

Found from outside: ``abh3 run CONFIG --headless --record logs/run.csv`` with
``plugins: {csv: {path: logs/run.csv}}`` runs, both writers interleave in one file, and
the run ends with exit 0 and "recorded 198 frames … to logs/run.csv" — ``abh3 decode``
then reads 72 of them (46 lines unreadable): the recording that should hold the stop
frames cannot be trusted. The same kind of collision as ``--socket X.sock --record
X.log`` (fixed): a mistake on the command line, exit 2 before anything opens.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.wallclock

ROOT = Path(__file__).resolve().parent.parent
CONFIG = """
buses:
  b: {interface: virtual, channel: probe-record-paths, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50}
plugins:
  csv: {path: run.csv}
"""


def test_record_onto_the_csv_plugins_file_is_a_usage_error(tmp_path: Path) -> None:
    (tmp_path / "robot.yaml").write_text(CONFIG)
    (tmp_path / "ctl").mkdir(mode=0o700)
    run = subprocess.run(
        [
            *(sys.executable, "-m", "abh3_supervisor", "run", "robot.yaml", "--headless"),
            *("--socket", "ctl/robot.sock", "--record", "run.csv"),
            *("--duration", "1", "--status-interval", "0"),
        ],
        cwd=tmp_path,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=60,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )
    assert "Traceback" not in run.stderr, run.stderr
    assert run.returncode == 2, run.stderr
    assert "run.csv" in run.stderr.splitlines()[-1], run.stderr
