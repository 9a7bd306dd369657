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


@pytest.mark.wallclock
def test_ruff_lint_and_format() -> None:
    lint = tool("ruff", "check", ".")
    assert lint.returncode == 0, lint.stdout
    fmt = tool("ruff", "format", "--check", ".")
    assert fmt.returncode == 0, fmt.stdout


@pytest.mark.wallclock
def test_mypy_strict() -> None:
    out = tool("mypy")
    assert out.returncode == 0, out.stdout


def test_the_core_never_imports_textual_or_plugin_dependencies() -> None:
    """Every module outside ``clients/`` loads without a UI or plugin dependency."""
    code = (
        "import sys, pkgutil, importlib, abh3_supervisor\n"
        "for m in pkgutil.walk_packages(abh3_supervisor.__path__, 'abh3_supervisor.'):\n"
        "    if not m.name.startswith(('abh3_supervisor.clients', 'abh3_supervisor.__main__')):\n"
        "        importlib.import_module(m.name)\n"
        "import abh3_supervisor.clients.cli, abh3_supervisor.clients.decode\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in "
        "{'textual', 'rich', 'cyclonedds', 'rclpy', 'evdev'}); print(bad); sys.exit(bool(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


# what each folder may import of ours (docs/architecture.md, "Package layout")
SANS_IO = {"errors", "protocol", "params"}
DOMAIN = SANS_IO | {"config", "core", "scheduler"}
ALLOWED = {
    "protocol": {"errors", "protocol"},
    "params": SANS_IO,  # sans-I/O like protocol
    "config": SANS_IO | {"config", "core"},  # startup: commands are dry-run
    "core": DOMAIN,
    "scheduler": DOMAIN,
    "plugin_host": DOMAIN - {"params"} | {"plugin_host"},
    "service": DOMAIN | {"runtime", "plugin_host", "service"},
    "simulator": DOMAIN | {"simulator"},
    # a python-can interface any program can load: nothing of ours but itself
    "wacousb": {"wacousb"},
    "runtime": DOMAIN | {"runtime", "plugin_host", "service", "simulator"},
    "commission": DOMAIN | {"commission"},  # sans-I/O: its bench and operator are given
}


def test_each_folder_imports_only_what_the_layout_allows() -> None:
    import ast

    root = Path(__file__).parent.parent / "abh3_supervisor"
    wrong: list[str] = []
    for folder, allowed in ALLOWED.items():
        for path in (root / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = (
                    [node.module or ""]
                    if isinstance(node, ast.ImportFrom)
                    else [a.name for a in node.names]
                    if isinstance(node, ast.Import)
                    else []
                )
                for name in names:
                    if not name.startswith("abh3_supervisor."):
                        continue
                    ours = name.removeprefix("abh3_supervisor.")
                    if not any(ours == a or ours.startswith(a + ".") for a in allowed):
                        wrong.append(f"{path.relative_to(root)} imports {name}")
    assert not wrong, "\n".join(wrong)
