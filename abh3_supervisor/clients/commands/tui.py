"""``abh3 tui``: the terminal UI attached to a running supervisor."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import connecting, not_terminals
from abh3_supervisor.errors import RunError


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    tui = sub.add_parser("tui", help="attach the terminal UI to a running supervisor")
    connecting(tui)
    tui.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    import asyncio

    from abh3_supervisor.clients.control import find_socket
    from abh3_supervisor.clients.tui.run import attach

    if redirected := not_terminals():
        raise RunError(f"{'/'.join(redirected)} not a terminal: the TUI needs one")
    path = find_socket(args.connect)
    release()
    return asyncio.run(attach(path, owner=False))
