"""A headless supervisor (``abh3 run configs/demo.yaml --headless``) in a process of its own."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent


@dataclass
class HeadlessRun:
    """What a headless run logged after both units came online (filled when it ends)."""

    log: str = ""


@contextlib.contextmanager
def headless_demo(sock: Path) -> Iterator[HeadlessRun]:
    """``abh3 run configs/demo.yaml --headless`` serving ``sock`` in a process of its own,
    entered once both units are online; on leaving, SIGTERM, and it must exit 0."""
    serve = ["--headless", "--socket", str(sock), "--status-interval", "0"]
    run = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", "configs/demo.yaml", *serve],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert run.stderr is not None
    served = HeadlessRun()
    try:
        for line in run.stderr:
            if "unit right: online" in line:  # serving starts before: both are up now
                break
        yield served
    finally:
        run.terminate()
        served.log = run.stderr.read()
        assert run.wait(30) == 0, served.log
