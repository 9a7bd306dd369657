"""Probe (issue 29): ``--read-only-socket`` naming the control socket's own file.

docs/service.md: "The socket is bound before the first CAN frame — whatever about the path
can fail, fails before any drive is commanded, with one line and exit 2". Found from
outside: the same path given to both options opens the buses, runs the start-up, then
ends in a ``KeyError`` traceback and exit 1; the same file spelled another way (relative
and absolute) runs on with the read-only server in the control socket's place — the log
says "serving the control socket …", and ``abh3 estop`` there is refused
(``this connection is read-only``): no e-stop through the socket, no command at all.
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
  b: {interface: virtual, channel: probe-socket-paths, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50, startup: ["SERVO ON ON"]}
"""


@pytest.mark.parametrize("spelling", ["same", "absolute"])
def test_read_only_socket_on_the_control_socket_is_a_usage_error(
    tmp_path: Path, spelling: str
) -> None:
    (tmp_path / "robot.yaml").write_text(CONFIG)
    (tmp_path / "ctl").mkdir(mode=0o700)
    control = "ctl/robot.sock"
    read_only = control if spelling == "same" else str(tmp_path / control)
    run = subprocess.run(
        [
            *(sys.executable, "-m", "abh3_supervisor", "run", "robot.yaml", "--headless"),
            *("--socket", control, "--read-only-socket", read_only),
            *("--record", "run.log", "--duration", "1", "--status-interval", "0"),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )
    assert "Traceback" not in run.stderr, run.stderr
    assert run.returncode == 2, run.stderr
    assert "read-only" in run.stderr.splitlines()[-1], run.stderr
    recording = tmp_path / "run.log"
    frames = recording.read_text().count("#") if recording.exists() else 0
    assert frames == 0, "the buses were opened before the mistake was found"
