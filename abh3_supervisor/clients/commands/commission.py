"""``abh3 commission``: its parser and session are clients/commission.py's; this registers
them."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from abh3_supervisor.clients import commission

    commission.add_parser(sub)
    sub.choices["commission"].set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import commission

    return commission.run(args)
