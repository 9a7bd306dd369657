"""``abh3 status``: the state of a running supervisor (exit 0: all online)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import connecting


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    status = sub.add_parser("status", help="the state of a running supervisor (exit 0: all online)")
    connecting(status)
    status.add_argument("--json", action="store_true", help="the whole state as JSON")
    status.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import control

    return control.status(control.find_socket(args.connect), args.json)
