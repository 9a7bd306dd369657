"""``abh3 param``: its parser and operations are clients/param.py's; this registers them."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from abh3_supervisor.clients import param

    param.add_parser(sub)
    sub.choices["param"].set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import param

    return param.run(args)
