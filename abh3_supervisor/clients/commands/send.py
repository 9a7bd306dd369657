"""``abh3 send``: one command of the seed's language to a running supervisor's units."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import connecting


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    send = sub.add_parser(
        "send",
        help="send a command to a running supervisor",
        description="Send one command of the seed's language to named units. Motion (a "
        "non-zero VEL or CUR) belongs to a client that is present: it needs --hold, which "
        "keeps it until Ctrl-C (or SIGTERM/SIGHUP) and stops it then.",
    )
    send.add_argument("text", help="a command of the seed's language, e.g. 'SERVO ON ON'")
    target = send.add_mutually_exclusive_group()
    target.add_argument("--unit", action="append", default=[], help="a unit (repeat for more)")
    target.add_argument("--all", action="store_true", help="every commanded unit")
    send.add_argument(
        "--hold",
        action="store_true",
        help="keep the session: motion holds until Ctrl-C, SIGTERM or SIGHUP, then stops",
    )
    connecting(send)
    send.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import control

    path = control.find_socket(args.connect)
    return control.send(path, args.text, args.unit, every=args.all, hold=args.hold)
