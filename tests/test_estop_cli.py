"""`abh3 estop` from a script or another terminal, end to end: a served supervisor on the
simulator, a client holding motion, the e-stop — judged from the CAN recording: each unit's
frames go from moving (START on) straight to zero with START off, and stay so."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from abh3_supervisor.protocol import flags, frames
from tests.support.cli import abh3
from tests.support.safe_word import commands_to

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
LAYOUTS = {1: flags.LAYOUT_2021, 3: flags.LAYOUT_2023}  # configs/demo.yaml, host 2


def commands(record: Path) -> dict[int, list[frames.Dp0Command]]:
    return {abh3: commands_to(record, abh3, lay.generation) for abh3, lay in LAYOUTS.items()}


def test_estop_from_the_command_line_stops_every_unit_and_a_holder_is_told(
    tmp_path: Path,
) -> None:
    sock, ro, record = tmp_path / "run" / "demo.sock", tmp_path / "ro.sock", tmp_path / "r.log"
    serve = ["--headless", "--socket", str(sock), "--read-only-socket", str(ro)]
    run = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", "configs/demo.yaml", *serve,
         "--status-interval", "0", "--record", str(record)],
        stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    assert run.stderr is not None
    holder: subprocess.Popen[str] | None = None
    try:
        for line in run.stderr:
            if "unit right: online" in line:
                break
        holder = subprocess.Popen(
            [sys.executable, "-m", "abh3_supervisor", "send", "VEL 100 0", "--unit", "left",
             "--hold", "--connect", str(sock)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
        )  # fmt: skip
        assert holder.stderr is not None
        assert "holding 'VEL 100 0' on left" in holder.stderr.readline()
        refused = abh3("estop", "--connect", str(ro))
        assert refused.returncode == 1
        assert refused.stderr == "error: estop: this connection is read-only\n"

        stopped = abh3("estop", "--connect", str(sock))
        assert stopped.returncode == 0, stopped.stderr
        assert stopped.stdout == (
            f"{sock}: EMERGENCY STOP latched: every commanded unit zero, START off (clear "
            "it with `abh3 estop --clear`)\n"
        )
        assert holder.wait(10) == 1
        told = holder.stderr.read()
        assert "left: the motion held by this command ended: the emergency stop is latched" in told
        status = abh3("status", "--connect", str(sock))
        assert status.returncode == 1 and status.stdout.startswith("EMERGENCY STOP latched")
        cleared = abh3("estop", "--clear", "--connect", str(sock))
        assert cleared.returncode == 0 and "emergency stop cleared" in cleared.stdout
        assert abh3("status", "--connect", str(sock)).returncode == 0
    finally:
        if holder is not None and holder.poll() is None:
            holder.kill()
            holder.wait()
        run.terminate()
        rest = run.stderr.read()
        assert run.wait(30) == 0, rest
    for abh3_id, sent in commands(record).items():
        start = LAYOUTS[abh3_id].start.both
        moving = [i for i, c in enumerate(sent) if c.inputs & start and (c.cmd_ay or c.cmd_bx)]
        assert moving, f"drive {abh3_id} never moved"
        after = sent[moving[-1] + 1 :]
        assert after, f"drive {abh3_id}: nothing after it moved"
        # the frame after the last moving one is the e-stop's (a lapse would keep START on)
        assert after[0].inputs & start == 0 and (after[0].cmd_ay, after[0].cmd_bx) == (0.0, 0.0)
        assert all(c.inputs & start == 0 and not (c.cmd_ay or c.cmd_bx) for c in after)


def test_estop_without_a_supervisor_says_so(tmp_path: Path) -> None:
    out = abh3("estop", "--connect", str(tmp_path / "none.sock"))
    assert out.returncode == 1 and out.stdout == ""
    assert f"error: no supervisor serves {tmp_path / 'none.sock'}" in out.stderr


def test_estop_without_connect_latches_every_supervisor_serving(tmp_path: Path) -> None:
    """Two supervisors in the default place: `abh3 estop` latches both (a refusal for
    want of a choice stopped nothing), and each drive's next frame is the stop; `--clear`
    still asks which."""
    runtime = tmp_path / "xdg"
    runtime.mkdir(mode=0o700)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(runtime)}
    runs, records = [], {}
    try:
        for config in ("demo", "skid-steer-demo"):
            records[config] = tmp_path / f"{config}.log"
            run = subprocess.Popen(
                [sys.executable, "-m", "abh3_supervisor", "run", f"configs/{config}.yaml",
                 "--headless", "--status-interval", "0", "--record", str(records[config])],
                stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env,
            )  # fmt: skip
            runs.append(run)
            assert run.stderr is not None
            for line in run.stderr:
                if "serving the control socket" in line:
                    break
        socks = sorted((runtime / "abh3").glob("*.sock"))
        assert [s.name for s in socks] == ["demo.sock", "skid-steer-demo.sock"]
        refused = abh3("estop", "--clear", env=env)
        assert refused.returncode == 1 and "several supervisors serve" in refused.stderr
        stopped = abh3("estop", env=env)
        assert stopped.returncode == 0, stopped.stderr
        assert stopped.stdout.splitlines() == [
            f"{sock}: EMERGENCY STOP latched: every commanded unit zero, START off (clear "
            "it with `abh3 estop --clear`)"
            for sock in socks
        ]
        for sock in socks:
            status = abh3("status", "--connect", str(sock), env=env)
            assert status.stdout.startswith("EMERGENCY STOP latched"), status.stdout
    finally:
        for run in runs:
            run.terminate()
        for run in runs:
            assert run.stderr is not None
            rest = run.stderr.read()
            assert run.wait(30) == 0, rest
    # the drives' side (demo.yaml): once the e-stop came, no frame to either drive moves
    for abh3_id, sent in commands(records["demo"]).items():
        start = LAYOUTS[abh3_id].start.both
        moving = [i for i, c in enumerate(sent) if c.inputs & start and (c.cmd_ay or c.cmd_bx)]
        assert moving and moving[-1] < len(sent) - 1, f"drive {abh3_id}"
        assert all(c.inputs & start == 0 for c in sent[moving[-1] + 1 :])
