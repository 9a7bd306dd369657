"""``abh3 run --exit-with-stdin`` (the TUI's child) whose stdin the loop cannot watch
(``/dev/null``, a file): nobody can be outlived, so it stops at once — cleanly, without
a traceback (a new-user trial found one)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CONFIG = """
buses: {b: {interface: virtual, channel: stdin-null, simulate: true}}
units:
  - {name: u, abh3_id: 1, command_rate_hz: 50, broadcast: {mask: 0}}
"""


@pytest.mark.wallclock  # a real `abh3 run` in a subprocess
def test_stdin_that_cannot_be_watched_stops_the_run_cleanly(tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(CONFIG)
    done = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "run", str(config), "--headless",
         "--no-socket", "--exit-with-stdin", "--duration", "30"],
        stdin=subprocess.DEVNULL, capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert "the TUI that started this supervisor is gone: stop" in done.stderr
