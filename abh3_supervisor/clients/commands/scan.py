"""``abh3 scan``: find the ABH3 drives on a bus (clients/scan.py); sends requests only."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from abh3_supervisor.clients.argtypes import positive


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    scan = sub.add_parser(
        "scan", help="find the ABH3 drives on a bus (sends requests only: moves nothing)"
    )
    scan.add_argument("--interface", required=True, help="python-can interface, e.g. socketcan")
    scan.add_argument("--channel", required=True, help="e.g. can0, /dev/ttyACM0")
    scan.add_argument(
        "--bitrate",
        type=int,
        default=500_000,
        choices=(250_000, 500_000, 1_000_000),
        help="bit/s (default 500000)",
    )
    scan.add_argument(
        "--host", type=_address, default=2, help="our address, 0–253 (default 2, the seed's)"
    )
    scan.add_argument(
        "--listen-only", action="store_true", help="send nothing; learn from the traffic there"
    )
    scan.add_argument(
        "--listen",
        type=positive,
        metavar="S",
        help="listen S seconds first (default 0.3; with --listen-only 5)",
    )
    scan.add_argument(
        "--yaml", action="store_true", help="print a starting configuration (the table: stderr)"
    )
    scan.set_defaults(func=handle)


def _address(text: str) -> int:
    if not text.isdigit() or not 0 <= int(text) <= 253:
        raise argparse.ArgumentTypeError(f"'{text}' is not an address 0–253")
    return int(text)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.scan import scan_command

    return scan_command(
        args.interface,
        args.channel,
        args.bitrate,
        host=args.host,
        listen_only=args.listen_only,
        listen_s=args.listen,
        as_yaml=args.yaml,
    )
