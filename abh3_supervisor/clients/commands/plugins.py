"""``abh3 plugins``: the installed plugins (clients/plugins.py); with CONFIG, which it
enables."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    plugins = sub.add_parser(
        "plugins",
        help="the installed plugins: version, API version, hooks; with CONFIG, which it enables",
    )
    plugins.add_argument("config", type=Path, nargs="?", metavar="CONFIG")
    plugins.add_argument("--json", action="store_true", help="machine-readable output")
    plugins.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.plugins import plugins_command

    return plugins_command(args.config, args.json)
