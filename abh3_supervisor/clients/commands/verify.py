"""``abh3 verify``: a running supervisor reads the drives' CAN settings again and compares
them with its file."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.cli import connecting


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    verify = sub.add_parser(
        "verify",
        help="a running supervisor compares drives' CAN settings with its file again",
        description="Ask a running supervisor to read the drives' CAN settings again and "
        "compare them with its YAML; a unit that verify: refuse holds is released when they "
        "now agree (its startup: commands run then). Exit 0 when every one agrees.",
    )
    verify.add_argument("units", nargs="+", metavar="UNIT")
    connecting(verify)
    verify.add_argument("--json", action="store_true", help="the results as JSON")
    verify.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients import control
    from abh3_supervisor.clients.drives import verify_running

    return verify_running(control.find_socket(args.connect), args.units, args.json)
