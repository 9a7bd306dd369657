"""``abh3 fleet``: its parser and view are clients/fleet/'s; this registers them."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import not_terminals


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from abh3_supervisor.clients.fleet import run

    run.add_parser(sub)
    sub.choices["fleet"].set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.fleet.run import options, run

    opts = options(args)  # a mistake in the options is said (exit 2) before anything else
    release()  # the view handles its own keys and signals
    return run(args, opts, not_terminals)
