"""``abh3 estop``: latch (or ``--clear``) a running supervisor's emergency stop."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import connecting


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    estop = sub.add_parser(
        "estop",
        help="latch a running supervisor's emergency stop (scripts, another terminal)",
        description="Latch the emergency stop of a running supervisor: every commanded unit "
        "gets zero and START off at once, and motion is refused until it is cleared. Without "
        "--connect, every supervisor of yours serving in the default place latches it. Exit 0 "
        "once each confirms; 1 when one cannot be reached or refuses (use the hardware "
        "e-stop then).",
    )
    estop.add_argument(
        "--clear",
        action="store_true",
        help="clear the latch instead (nothing moves until START and motion are given again)",
    )
    connecting(estop)
    estop.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import control

    if not args.clear:  # every one served, where not told which
        return control.estop_every(control.find_sockets(args.connect))
    return control.estop(control.find_socket(args.connect), clear=True)
