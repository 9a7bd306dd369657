"""``kill -9`` during a run: what each recording format keeps (at most its last second
lost), and a write error's exit code — ``abh3 run`` in a subprocess, as a user runs it."""

from __future__ import annotations

import csv
import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "configs" / "demo.yaml"
RATE_HZ = 50  # the demo's command_rate_hz: DP0 commands of unit left per second
KILL_AFTER_S = 2.0  # after the file first holds data
HAS_DATA = 2048  # bytes: more than any format's header
FORMATS = [".log", ".asc", ".blf", ".csv", ".mcap", "csv plugin"]


def abh3(*args: str) -> list[str]:
    return [sys.executable, "-m", "abh3_supervisor", *args]


def started(cmd: list[str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as err:
        return subprocess.Popen(cmd, cwd=ROOT, stderr=err, stdin=subprocess.DEVNULL)


def ran_for(proc: subprocess.Popen[bytes], seconds: float) -> bool:
    """Wait on the process (not a sleep): True when it is still running after ``seconds``."""
    try:
        proc.wait(timeout=seconds)
    except subprocess.TimeoutExpired:
        return True
    return False


def wait_for_data(proc: subprocess.Popen[bytes], path: Path, log: Path) -> None:
    for _ in range(600):  # a 30 s deadline, 50 ms at a time
        if path.exists() and path.stat().st_size > HAS_DATA:
            return
        assert ran_for(proc, 0.05), log.read_text()
    raise AssertionError(f"{path} never held data:\n{log.read_text()}")


def left_commands(path: Path) -> list[float]:
    """Wall-clock times of unit left's DP0 commands in what is left of the recording."""
    if path.suffix == ".csv" and path.name.startswith("plugin"):  # the csv plugin's rows
        with path.open(encoding="utf-8", newline="") as f:
            return [float(r["time [s]"]) for r in csv.DictReader(f) if r["unit"] == "left"]
    out = subprocess.run(
        abh3("decode", str(path), "--config", str(DEMO), "--json"),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr  # abh3 decode reads what a kill left
    rows = [json.loads(line) for line in out.stdout.splitlines()]
    times = [r["t"] for r in rows if r.get("unit") == "left" and r["kind"] == "dp0_command"]
    if path.suffix == ".asc":  # decode gives times from the first frame: add its wall clock
        first = next(iter(can.ASCReader(str(path), relative_timestamp=False)))
        times = [t + first.timestamp - float(rows[0]["t"]) for t in times]
    return times


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_kill_9_loses_at_most_the_last_second_of_a_recording(tmp_path: Path, fmt: str) -> None:
    log = tmp_path / "stderr.log"
    if fmt == "csv plugin":
        path = tmp_path / "plugin.csv"  # flushed every flush_s (0.5 s)
        config = tmp_path / "demo-csv.yaml"
        config.write_text(DEMO.read_text() + f"plugins:\n  csv: {{path: '{path}'}}\n")
        cmd = abh3("run", str(config), "--headless", "--no-socket")
    else:
        path = tmp_path / f"run{fmt}"
        cmd = abh3("run", str(DEMO), "--headless", "--no-socket", "--record", str(path))
    proc = started(cmd, log)
    try:
        wait_for_data(proc, path, log)
        # a different moment in the flush period for each format
        assert ran_for(proc, KILL_AFTER_S + 0.09 * FORMATS.index(fmt)), log.read_text()
        killed_at = time.time()
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    times = left_commands(path)
    assert len(times) >= RATE_HZ, f"{len(times)} commands kept"
    assert killed_at - times[-1] <= 1.0  # the last one kept: at most a second old
    # and nothing lost before it: every command since the first, at the configured rate
    # (a loaded machine's rate shortfall counts as loss here: the bound has room for it)
    expected = RATE_HZ * (killed_at - times[0])
    lost = expected - len(times)
    assert lost <= RATE_HZ * 1.0, f"{lost:.0f} of {expected:.0f} commands lost"


def test_a_recording_cut_short_by_a_write_error_is_exit_code_5(tmp_path: Path) -> None:
    path = tmp_path / "small.log"

    def small_files() -> None:  # as a full disk: no file of this process beyond 16 KiB
        resource.setrlimit(resource.RLIMIT_FSIZE, (16 << 10, 16 << 10))

    run = subprocess.run(
        [
            *abh3("run", str(DEMO), "--headless", "--no-socket", "--duration", "3"),
            "--record",
            str(path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        preexec_fn=small_files,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )
    assert run.returncode == 5, run.stderr
    assert "File too large" in run.stderr
    assert f"recording {path.resolve()} stopped early, at " in run.stderr
    assert "stopped early on a write error" in run.stderr and "(exit code 5)" in run.stderr
    assert run.stderr.count("stop frame confirmed by the drive") == 2
    assert "Traceback" not in run.stderr
    assert 0 < path.stat().st_size <= 16 << 10 and path.read_text().endswith("\n")
