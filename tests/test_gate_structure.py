"""One motion gate, by construction: the code itself has one place that builds a command
word that can move a motor, and one way it reaches a scheduler. Read from the source, so
a second path added later fails here whatever the other tests exercise."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).parent.parent / "abh3_supervisor"
PLUGINS = Path(__file__).parent.parent / "plugins"


def calls(name: str) -> dict[str, list[str]]:
    """Module path → the source of each call of ``…name(…)`` in the product's code."""
    found: dict[str, list[str]] = {}
    for root in (PACKAGE, PLUGINS):
        for path in sorted(root.rglob("*.py")):
            tree = ast.parse(path.read_text(), str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Call):
                    func = node.func
                    called = (
                        func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
                    )
                    if called == name:
                        rel = str(path.relative_to(root.parent))
                        found.setdefault(rel, []).append(ast.unparse(node))
    return found


def test_only_the_gate_encodes_a_command_word_that_can_move() -> None:
    found = calls("encode_dp0_command")
    assert set(found) == {
        "abh3_supervisor/core/gate.py",  # Word.payload: every word a unit is sent
        "abh3_supervisor/scheduler/core.py",  # the all-zero word before the first push
        "abh3_supervisor/core/planner.py",  # counts the bits of an idle word, never sent
    }
    assert found["abh3_supervisor/scheduler/core.py"] == ["frames.encode_dp0_command(0, 0, 0)"]
    assert found["abh3_supervisor/core/planner.py"] == ["frames.encode_dp0_command(0, 0, inputs)"]


def test_only_the_supervisors_push_hands_a_word_to_a_scheduler() -> None:
    found = calls("set_payload")
    assert list(found) == ["abh3_supervisor/core/supervisor.py"]
    assert len(found["abh3_supervisor/core/supervisor.py"]) == 1
    source = (PACKAGE / "core" / "supervisor.py").read_text()
    push = source[source.index("    def _push(") : source.index("    def request_status(")]
    assert "self.gate.word(unit, owned, ready)" in push and "word.payload()" in push


def test_no_plugin_or_client_sets_a_units_switches_or_setpoint_directly() -> None:
    """``unit.inputs = …`` / ``unit.setpoint = …`` only in the core (the gate's callers)."""
    offenders = []
    for root in (PACKAGE, PLUGINS):
        for path in sorted(root.rglob("*.py")):
            rel = str(path.relative_to(root.parent))
            if rel.startswith(
                (
                    "abh3_supervisor/core/",
                    "abh3_supervisor/clients/mirror.py",
                    "abh3_supervisor/simulator/",
                )
            ):
                continue  # the core; a client's mirror of pushed state; the simulated drive
            tree = ast.parse(path.read_text(), rel)
            for node in ast.walk(tree):
                if isinstance(node, ast.Assign):
                    targets = node.targets
                elif isinstance(node, ast.AugAssign):
                    targets = [node.target]
                else:
                    continue
                for target in targets:
                    if isinstance(target, ast.Attribute) and target.attr in ("inputs", "setpoint"):
                        offenders.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
    assert not offenders, "\n".join(offenders)
