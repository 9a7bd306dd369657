"""Lint, types and the core's import boundary are part of the one test command."""

from __future__ import annotations

import ast
import re
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
        "{'textual', 'rich', 'cyclonedds', 'rclpy', 'evdev', 'paho'}); print(bad); sys.exit(bool(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


PACKAGE = ROOT / "abh3_supervisor"
LAYOUT = ROOT / "docs/architecture.md"  # its "Package layout" table is the rule


def layout_rules() -> dict[str, set[str] | None]:
    """The table in docs/architecture.md: each folder or module of the package and what of
    ours it may import besides itself (None: anything)."""
    section = LAYOUT.read_text().split("\n## Package layout\n", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `([\w.]+?)(?:/|\.py)?` \|.*\| ([^|]+) \|$", section, re.M)
    rules: dict[str, set[str] | None] = {}
    for name, cell in rows:
        cell = cell.strip()
        rules[name] = (
            None
            if cell == "anything"
            else set()
            if cell == "nothing of ours"
            else set(re.findall(r"`(\w+)`", cell))
        )
    return rules


def ours(module: str) -> list[str]:
    """The top-level folders or modules of the package that importing ``module`` names."""
    parts = module.split(".")
    return [parts[1]] if parts[0] == "abh3_supervisor" and len(parts) > 1 else []


def imports_of_ours(path: Path) -> set[str]:
    """Every folder or module of ours ``path`` imports, wherever in it the import is."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(top for a in node.names for top in ours(a.name))
        elif isinstance(node, ast.ImportFrom) and node.module == "abh3_supervisor":
            # `from abh3_supervisor import X`: a folder or module, or the package's own
            # names (`__version__`), which anyone may read
            found.update(a.name for a in node.names if (PACKAGE / a.name).exists())
            found.update(a.name for a in node.names if (PACKAGE / f"{a.name}.py").exists())
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            found.update(ours(node.module or ""))
        elif isinstance(node, ast.ImportFrom):
            found.add("<a relative import>")  # the rule reads absolute names only
    return found


def test_the_layout_table_covers_the_package_and_names_only_what_exists() -> None:
    rules = layout_rules()
    tops = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    tops |= {p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__"}
    assert set(rules) == tops, "docs/architecture.md's Package layout: a row per folder"
    named = {n for allowed in rules.values() if allowed is not None for n in allowed}
    assert named <= tops, f"the table allows what does not exist: {named - tops}"


def test_each_folder_imports_only_what_the_layout_allows() -> None:
    wrong: list[str] = []
    for top, allowed in layout_rules().items():
        if allowed is None:
            continue
        paths = [PACKAGE / f"{top}.py"] if (PACKAGE / f"{top}.py").exists() else []
        for path in paths or sorted((PACKAGE / top).rglob("*.py")):
            for name in sorted(imports_of_ours(path) - allowed - {top}):
                wrong.append(f"{path.relative_to(PACKAGE)} imports {name}")
    assert not wrong, "not allowed by docs/architecture.md's Package layout:\n" + "\n".join(wrong)


def test_the_import_rule_sees_every_form_of_import(tmp_path: Path) -> None:
    """The check above would pass vacuously if it missed a form: each is found."""
    path = tmp_path / "m.py"
    path.write_text(
        "import abh3_supervisor.core.state\n"
        "from abh3_supervisor.service import server\n"
        "from abh3_supervisor import runtime, __version__\n"
        "def f() -> None:\n"
        "    from abh3_supervisor.clients.tui import app\n"
        "from . import sibling\n"
    )
    found = imports_of_ours(path)
    assert found == {"core", "service", "runtime", "clients", "<a relative import>"}


def modules_imported(path: Path) -> set[str]:
    """Every module ``path`` imports, by its full name, wherever in it the import is
    (``from a.b import c`` names ``a.b`` and ``a.b.c``: ``c`` may be a module)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            found.add(base)
            found.update(f"{base}.{a.name}" if node.module else base + a.name for a in node.names)
    return found


def test_the_core_has_no_clock_and_starts_no_thread() -> None:
    """The core is sans-I/O (docs/architecture.md): it is given the time and called on the
    loop; the threads and the clock of the input sources' feed are the plugin host's
    (plugin_host/feed.py)."""
    wrong = [
        f"{path.relative_to(PACKAGE)} imports {name}"
        for path in sorted((PACKAGE / "core").glob("*.py"))
        for name in sorted(modules_imported(path))
        if name.split(".")[0] in ("time", "threading")
    ]
    assert not wrong, "\n".join(wrong)


def test_the_arbitration_does_not_import_the_supervisor() -> None:
    """core/inputs.py knows the supervisor only as the protocol it names (``Commander``):
    the supervisor imports the arbitration, never the other way round."""
    names = modules_imported(PACKAGE / "core" / "inputs.py")
    assert not names & {"abh3_supervisor.core.supervisor", ".supervisor"}, names


def test_the_import_checks_see_every_form(tmp_path: Path) -> None:
    path = tmp_path / "m.py"
    path.write_text(
        "import time\n"
        "from threading import Lock\n"
        "from abh3_supervisor.core import supervisor\n"
        "def f() -> None:\n"
        "    import time as clock\n"
        "from . import supervisor\n"
    )
    found = modules_imported(path)
    assert {"time", "threading", "abh3_supervisor.core.supervisor", ".supervisor"} <= found
