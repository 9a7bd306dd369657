"""What the docs state about the code is read from the code: figures that name their
constant, the stop's condition, the control socket's methods, what a read-only socket
answers and its permissions, the commands and options shown, the scripted faults.

(The package layout's import rules are read from docs/architecture.md by test_quality.py.)
"""

from __future__ import annotations

import argparse
import ast
import grp
import importlib
import math
import os
import re
import stat
from pathlib import Path

import pytest

from abh3_supervisor.clients import cli
from abh3_supervisor.config.model import FaultKind
from abh3_supervisor.service import server

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "abh3_supervisor"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# "1 s (`stopping.STOP_DEADLINE_S`)": a figure, its unit, then the constant it is
CITED = re.compile(r"(\d+(?:\.\d+)?) (ms|s) \(`((?:\w+\.)*)([A-Z][A-Z0-9_]*)`\)")
# claims that must stay tied to their constant, and where they are made
REQUIRED = {
    "stopping.STOP_DEADLINE_S": {"README.md", "architecture.md", "plugins.md"},
    "stopping.STOP_RETRY_S": {"architecture.md"},
}


def citations() -> list[tuple[str, float, str, str]]:
    """(document, the figure in seconds, the qualifier, the constant's name)."""
    found = []
    for doc in DOCS:
        text = re.sub(r"\s+", " ", doc.read_text())  # a citation may wrap
        for figure, unit, qualifier, name in CITED.findall(text):
            seconds = float(figure) / (1000 if unit == "ms" else 1)
            found.append((doc.name, seconds, qualifier.rstrip("."), name))
    return found


def constant(qualifier: str, name: str) -> float:
    """The module-level ``name`` of the one module of ours whose dotted path ends with
    ``qualifier`` and defines it."""
    owners = []
    for path in PACKAGE.rglob("*.py"):
        dotted = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        if qualifier and not dotted.endswith(f".{qualifier}"):
            continue
        for node in ast.parse(path.read_text()).body:
            targets = node.targets if isinstance(node, ast.Assign) else []
            targets += [node.target] if isinstance(node, ast.AnnAssign) else []
            if any(isinstance(t, ast.Name) and t.id == name for t in targets):
                owners.append(dotted)
    assert len(owners) == 1, f"`{qualifier}.{name}`: defined in {owners or 'no module'}"
    value = getattr(importlib.import_module(owners[0]), name)
    assert isinstance(value, int | float)
    return value / 1000 if name.endswith("_MS") else value


def test_every_figure_that_names_its_constant_is_that_constant() -> None:
    found = citations()
    wrong = [
        f"{doc}: {seconds:g} s, but {qualifier + '.' if qualifier else ''}{name} is "
        f"{constant(qualifier, name):g} s"
        for doc, seconds, qualifier, name in found
        if not math.isclose(seconds, constant(qualifier, name))
    ]
    assert not wrong, "\n".join(wrong)
    for name, docs in REQUIRED.items():
        citing = {doc for doc, _, qualifier, cited in found if f"{qualifier}.{cited}" == name}
        assert docs <= citing, f"{name} is no longer cited in {docs - citing}"


def test_the_stop_is_said_to_last_until_the_drive_reports_servo_and_start_off() -> None:
    """Not "until the drive answers": a reply proves nothing (runtime/stopping.py)."""
    for doc in DOCS:
        text = re.sub(r"\s+", " ", doc.read_text()).replace("*", "")
        for cited in re.finditer(r"\(`stopping\.STOP_DEADLINE_S`\)", text):
            before = text[max(0, cited.start() - 200) : cited.start()]
            assert "reports SERVO and START off" in before, f"{doc.name}: …{before}"


def methods_in_the_code() -> set[str]:
    """The keys of ``ControlServer``'s method table, read from its source."""
    tree = ast.parse((PACKAGE / "service/server.py").read_text())
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Attribute)
            and node.target.attr == "_methods"
            and isinstance(node.value, ast.Dict)
        ):
            names = {k.value for k in node.value.keys if isinstance(k, ast.Constant)}
            if None in node.value.keys:  # **{name: … for name in _FIELDS}: the motions
                names |= set(server._FIELDS)
            return {str(n) for n in names}
    pytest.fail("ControlServer's method table (self._methods) was not found")


def test_every_method_the_socket_serves_is_documented_and_no_other() -> None:
    service = (ROOT / "docs/service.md").read_text()
    code = methods_in_the_code()
    assert {"hello", "command", "estop", "param_write", "twist"} <= code  # the reader works
    undocumented = {m for m in code if f"`{m}`" not in service}
    assert not undocumented, f"docs/service.md does not mention {sorted(undocumented)}"
    tabled = set(re.findall(r"^\| `(\w+)` \|", service, re.M))  # the method tables' rows
    assert len(tabled) > 10 and not tabled - code, f"not served: {tabled - code}"


def test_the_read_only_socket_answers_what_the_docs_list() -> None:
    service = (ROOT / "docs/service.md").read_text()
    (row,) = re.findall(r"^\| `--read-only-socket PATH` \|.*$", service, re.M)
    listed = set(re.findall(r"`(\w+)`", row.split("answers only", 1)[1]))
    assert listed == server.READ_ONLY_METHODS
    assert methods_in_the_code() >= server.READ_ONLY_METHODS


def test_the_read_only_socket_is_owner_only_whatever_the_group(tmp_path: Path) -> None:
    """docs/service.md: `--socket-group` opens the control socket to a group, never the
    read-only one, which stays 0600 until its owner loosens it."""
    group = grp.getgrgid(os.getgid()).gr_name
    control, read_only = tmp_path / "ctl" / "a.sock", tmp_path / "ctl" / "a-ro.sock"
    bound = server.preflight(server.ServiceOptions(control, group, read_only))
    try:
        assert stat.S_IMODE(control.stat().st_mode) == 0o660
        assert stat.S_IMODE(read_only.stat().st_mode) == 0o600
    finally:
        server.release(bound)
    service = re.sub(r"\s+", " ", (ROOT / "docs/service.md").read_text())
    assert "The read-only socket is owner-only (0600) whatever `--socket-group` says" in service


def test_every_command_and_option_the_docs_show_exists() -> None:
    """`abh3 WORD` is a subcommand and `--option` an option of `abh3` (or of `python -m
    benchmarks`), in inline code and in code blocks alike."""
    subcommands: set[str] = set()
    options: set[str] = set()

    def walk(parser: argparse.ArgumentParser) -> None:
        for action in parser._actions:
            options.update(o for o in action.option_strings if o.startswith("--"))
            if isinstance(action, argparse._SubParsersAction):
                subcommands.update(action.choices)
                for sub in action.choices.values():
                    walk(sub)

    walk(cli._parser())
    for path in (ROOT / "benchmarks").glob("*.py"):
        options.update(re.findall(r"add_argument\(\s*\"(--[\w-]+)\"", path.read_text()))
    options |= {"--check", "--pdeathsig"}  # `ruff format --check`, `setpriv --pdeathsig`
    unit = ROOT / "docs/examples/systemd/abh3-supervisor.service"  # its ExecStart too
    unknown = []
    for doc in [*DOCS, unit]:
        text = doc.read_text()
        blocks = re.findall(r"^```[^\n]*\n(.*?)^```", text, re.M | re.S)
        lines = text.splitlines() if doc == unit else "\n".join(blocks).splitlines()
        for code in [*re.findall(r"`([^`\n]+)`", text), *lines]:
            words = re.findall(r"(?<![\w.-])abh3 ([a-z][\w-]*)", code)
            unknown += [f"{doc.name}: abh3 {w}" for w in words if w not in subcommands]
            ours = code.startswith("--") and doc.name != "testing.md"  # it shows pytest's
            if words or ours or "benchmarks" in code:
                flags = re.findall(r"(?<![\w-])(--[a-z][\w-]*)", code)
                unknown += [f"{doc.name}: {f} in {code!r}" for f in flags if f not in options]
    assert subcommands >= {"run", "send", "param"} and "--hold" in options  # the reader works
    assert not unknown, "\n".join(unknown)


def test_every_scripted_fault_is_documented() -> None:
    """In the reference, docs/configuration.md; docs/architecture.md only points there
    (a map a newcomer reads in ten minutes, issue 53)."""
    text = (ROOT / "docs" / "configuration.md").read_text()
    missing = [k.value for k in FaultKind if f"`{k.value}`" not in text]
    assert not missing, f"docs/configuration.md does not name the fault kinds {missing}"
    assert "`simulate.faults`" in (ROOT / "docs" / "architecture.md").read_text()
