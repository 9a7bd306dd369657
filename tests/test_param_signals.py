"""`abh3 param` and stop signals: every mode ends cleanly at once (no traceback), and a
restore that stops part way leaves a journal whose one command undoes it (exit 4)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from abh3_supervisor.params import files, table
from abh3_supervisor.params.files import ParamValue
from tests.support.headless import headless_demo

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
SIM = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: true}}
units:
  - {{name: left, abh3_id: 1}}
"""
# the speed, current, accel and gain tables: 80 values that are safe to change
TABLES = [e for e in table.PARAMETERS if 0x5000 <= e.address < 0x5078]


def abh3(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def config(tmp_path: Path, channel: str) -> Path:
    path = tmp_path / f"{channel}.yaml"
    path.write_text(SIM.format(channel=channel))
    return path


def wait_for(proc: subprocess.Popen[str], text: str) -> list[str]:
    """Lines of stderr up to the first that holds ``text``."""
    assert proc.stderr is not None
    seen = []
    for line in proc.stderr:
        seen.append(line)
        if text in line:
            return seen
    raise AssertionError(f"never saw {text!r}: {''.join(seen)[-2000:]}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGINT, signal.SIGTERM])
def test_monitor_at_a_millisecond_ends_cleanly_on_a_stop_signal(
    tmp_path: Path, sig: signal.Signals
) -> None:
    cfg = config(tmp_path, f"sig-mon-{sig.value}-{os.getpid()}")
    proc = abh3("param", "-c", str(cfg), "monitor", "left", "VELOCITY_AY", "--interval", "0.001")
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith("VELOCITY_AY=")  # running, on its own bus
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=5)
    assert proc.returncode == 128 + sig.value, err
    assert "Traceback" not in err and f"stopped by {sig.name}" in err


def test_a_restore_stopped_part_way_leaves_a_journal_that_undoes_it(tmp_path: Path) -> None:
    cfg = config(tmp_path, f"sig-restore-{os.getpid()}")
    wanted = tmp_path / "wanted.csv"
    files.write(
        wanted,
        [ParamValue(e.address, table.to_word(e.default + 1, e.kind)) for e in TABLES],
    )
    proc = abh3("param", "-c", str(cfg), "restore", "left", str(wanted), "--yes")
    wait_for(proc, f"[5/{len(TABLES)}]")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=5)
    assert proc.returncode == 4, err  # partial
    assert "Traceback" not in err and "stopped by SIGINT" in err
    assert "partial restore: " in err
    undo = next(line for line in err.splitlines() if line.startswith("undo: "))
    journal = Path(undo.split()[7])
    assert journal.parent == tmp_path and journal.exists()
    kept = files.read(journal)
    assert 5 <= len(kept) < len(TABLES)
    defaults = {e.address: table.to_word(e.default, e.kind) for e in TABLES}
    assert all(v.word == defaults[v.address] for v in kept)  # the old values


def test_the_journal_of_a_stopped_restore_undoes_it_on_a_running_supervisor(
    tmp_path: Path,
) -> None:
    """Through a running supervisor (its simulated drives keep what was written): stop a
    restore with SIGTERM part way, run the one command it printed, and the drive holds
    what it held before."""
    sock = tmp_path / "run" / "demo.sock"
    wanted = tmp_path / "wanted.csv"
    files.write(
        wanted,
        [ParamValue(e.address, table.to_word(e.default + 1, e.kind)) for e in TABLES],
    )
    before = tmp_path / "before.csv"
    with headless_demo(sock):
        where = ["--connect", str(sock)]
        assert abh3("send", "SERVO OFF OFF", "--unit", "left", *where).wait(30) == 0
        assert abh3("param", *where, "dump", "left", "-o", str(before)).wait(60) == 0
        proc = abh3("param", *where, "restore", "left", str(wanted), "--yes")
        wait_for(proc, f"[5/{len(TABLES)}]")
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=5)
        assert proc.returncode == 4 and "stopped by SIGTERM" in err, err
        undo = next(line for line in err.splitlines() if line.startswith("undo: "))
        assert undo.split()[1:5] == ["abh3", "param", "--connect", str(sock)]
        again = subprocess.run(
            [sys.executable, "-m", "abh3_supervisor", *undo.split()[2:]],
            cwd=ROOT, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert again.returncode == 0, again.stderr
        diff = subprocess.run(
            [sys.executable, "-m", "abh3_supervisor", "param", *where, "diff", "left",
             str(before)],
            cwd=ROOT, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert diff.returncode == 0, diff.stderr
        assert diff.stdout.endswith(f"0 parameter(s) of left differ from {before}\n")
