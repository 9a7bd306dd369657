"""``abh3 plugin new``: plugin authors' tools (clients/plugin_template.py)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from abh3_supervisor.clients.cli import EXIT_OK


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    plugin = sub.add_parser("plugin", help="plugin authors' tools")
    plugin.set_defaults(func=handle)
    tools = plugin.add_subparsers(dest="plugin", required=True, metavar="COMMAND")
    new = tools.add_parser(
        "new",
        help="write a pip-installable plugin package: an example hook, its test, pyproject",
    )
    new.add_argument("name", help="the plugin's name in the YAML (lowercase, digits, _)")
    new.add_argument(
        "--dir", type=Path, default=Path("."), metavar="D", help="create it in D (default: .)"
    )


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.plugin_template import new_plugin

    print(f"wrote {new_plugin(args.name, args.dir)}")
    return EXIT_OK
