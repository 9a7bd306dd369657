"""``abh3 --help`` and every subcommand's: exit 0, each option listed; and each subcommand
is a module of clients/commands/ holding its parser and its handler (``func``)."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from abh3_supervisor.clients import cli, commands

ROOT = Path(__file__).resolve().parent.parent


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser's subcommands by name (none: {})."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def every_parser(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """``abh3`` and each subcommand, nested ones (``param get``) too, with its words."""
    yield path, parser
    for name, sub in subparsers(parser).items():
        yield from every_parser(sub, (*path, name))


PARSERS = dict(every_parser(cli._parser()))


def shown(action: argparse.Action) -> list[str]:
    """What ``--help`` must show of an action: its options, or a positional's name."""
    if action.help == argparse.SUPPRESS:
        return []
    if action.option_strings:
        return list(action.option_strings)
    if isinstance(action, argparse._SubParsersAction):
        return list(action.choices)
    metavar = action.metavar if isinstance(action.metavar, str) else None
    return [metavar or action.dest]


@pytest.mark.parametrize("words", list(PARSERS), ids=lambda w: " ".join(w) or "abh3")
def test_every_help_exits_0_and_lists_its_options(
    words: tuple[str, ...], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as ended:
        cli.main([*words, "--help"])
    assert ended.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: {' '.join(('abh3', *words))} ")
    missing = [s for a in PARSERS[words]._actions for s in shown(a) if s not in out]
    assert not missing, f"abh3 {' '.join(words)} --help does not show {missing}"


def test_the_entry_point_help_lists_every_subcommand() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "--help"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    names = subparsers(PARSERS[()])
    assert {"run", "check", "status", "send", "estop", "param", "decode"} <= set(names)
    assert all(f"    {name}" in out.stdout for name in names)


def test_each_subcommand_has_its_handler_from_its_own_module() -> None:
    """Every subcommand's parser sets ``func``, a handler of a module of
    clients/commands/; a nested one (``param get``) gets its command's."""
    by_module: dict[str, list[str]] = {}
    for name, parser in subparsers(PARSERS[()]).items():
        func = parser.get_default("func")
        assert callable(func), f"abh3 {name}: no func default"
        assert func.__module__.startswith(f"{commands.__name__}."), (name, func.__module__)
        by_module.setdefault(func.__module__, []).append(name)
    for words, parser in PARSERS.items():
        if len(words) > 1:  # inherited from its command's parser: none of its own
            assert parser.get_default("func") is None, words
    modules = {f"{commands.__name__}.{m.name}" for m in pkgutil.iter_modules(commands.__path__)}
    assert set(by_module) == modules, "a module of clients/commands/ registers no command"
    for name in modules:
        module = importlib.import_module(name)
        assert callable(module.add_parser) and callable(module.handle), name
    assert by_module[f"{commands.__name__}.enable"] == ["enable", "disable"]


def test_the_handler_parsed_is_the_one_called(monkeypatch: pytest.MonkeyPatch) -> None:
    """``main`` dispatches through ``args.func``, with the exit code it returns."""
    seen: list[tuple[str, str]] = []

    def handle(args: argparse.Namespace, release: object) -> int:
        seen.append((args.cmd, args.op))
        return 7

    from abh3_supervisor.clients.commands import param

    monkeypatch.setattr(param, "handle", handle)
    assert cli.main(["param", "--config", "x.yaml", "get", "left", "VEL"]) == 7
    assert seen == [("param", "get")]
