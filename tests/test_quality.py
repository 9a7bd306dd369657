"""Lint, types and the core's import boundary are part of the one test command."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def tool(name: str, *args: str) -> subprocess.CompletedProcess[str]:
    exe = shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)
    if exe is None:
        pytest.fail(f"{name} is not installed: pip install -e '.[test]'")
    return subprocess.run([exe, *args], capture_output=True, text=True, cwd=ROOT, timeout=600)


def test_ruff_lint_and_format() -> None:
    lint = tool("ruff", "check", ".")
    assert lint.returncode == 0, lint.stdout
    fmt = tool("ruff", "format", "--check", ".")
    assert fmt.returncode == 0, fmt.stdout


def test_mypy_strict() -> None:
    out = tool("mypy")
    assert out.returncode == 0, out.stdout


def test_the_core_never_imports_textual_or_plugin_dependencies() -> None:
    code = (
        "import sys, abh3_supervisor.cli, abh3_supervisor.headless, abh3_supervisor.runtime, "
        "abh3_supervisor.decoding, abh3_supervisor.planner; "
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "{'textual', 'rich', 'cyclonedds', 'rclpy', 'evdev'}); print(bad); sys.exit(bool(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
