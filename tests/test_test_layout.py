"""The tests' own layout: scaffolding is shared through tests/support/, and a test module
never imports another (collecting one would run, or re-run, the other's fixtures)."""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).parent


def imported_test_modules(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = (
            [node.module or "", *(f"{node.module}.{a.name}" for a in node.names)]
            if isinstance(node, ast.ImportFrom)
            else [a.name for a in node.names]
            if isinstance(node, ast.Import)
            else []
        )
        found |= {n.removeprefix("tests.") for n in names if n.startswith(("tests.test_", "test_"))}
    return found


def test_test_modules_do_not_import_each_other() -> None:
    pairs = {
        (path.stem, other)
        for path in sorted(TESTS.glob("*.py"))
        for other in imported_test_modules(path)
    }
    assert not pairs, sorted(pairs)


def test_support_never_imports_a_test_module() -> None:
    for path in sorted((TESTS / "support").glob("*.py")):
        assert not imported_test_modules(path), path.name
