"""``abh3`` run to its end as a script runs it, from the checkout's root."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent


def abh3(
    *args: str, timeout: float = 60, env: Mapping[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """``abh3 ARGS``: its exit code, stdout and stderr (bounded)."""
    return subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
        env=env,
    )
