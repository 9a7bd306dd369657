"""The ``abh3`` subcommands: one module each, holding its parser and its handler.

Each module's ``add_parser(sub)`` adds its subcommand(s) to ``abh3``'s subparsers and sets
``func``, the handler :func:`abh3_supervisor.clients.cli.main` calls as
``func(args, release)`` (``release``: give the stop signals' handlers back, for a command
that handles its own keys and signals) and whose return is the exit code. The parsers are
built for every ``abh3`` command, so a module imports only what its parser needs at the
top; the rest (asyncio, YAML, the buses) loads in the handler.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from abh3_supervisor.clients.commands import (
    check,
    commission,
    decode,
    enable,
    estop,
    fleet,
    param,
    plugin,
    plugins,
    ros2,
    run,
    scan,
    schema,
    send,
    simulate,
    status,
    tui,
    verify,
)

if TYPE_CHECKING:
    import argparse


class Handler(Protocol):
    """A subcommand's handler: its exit code."""

    def __call__(self, args: argparse.Namespace, release: Callable[[], None]) -> int: ...


# in the order `abh3 --help` lists them
MODULES = (
    run,
    tui,
    status,
    estop,
    enable,  # and disable
    send,
    verify,
    simulate,
    check,
    scan,
    param,
    commission,
    fleet,
    plugins,
    plugin,
    schema,
    decode,
    ros2,
)


def add_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Every subcommand's parser, with its handler as ``func``."""
    for module in MODULES:
        module.add_parser(sub)
