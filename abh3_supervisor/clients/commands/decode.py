"""``abh3 decode``: a recording made with ``--record``, decoded (clients/decode.py)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from abh3_supervisor.clients.cli import EXIT_OK


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    dec = sub.add_parser("decode", help="decode a recording made with --record")
    dec.add_argument("file", type=Path)
    dec.add_argument("--config", type=Path, help="name units and pick protocol generations")
    dec.add_argument("--json", action="store_true", help="one JSON object per frame")
    dec.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.decode import decode_file
    from abh3_supervisor.config import load_config

    known = load_config(args.config) if args.config else None
    for out in decode_file(args.file, known, args.json):
        print(out)
    return EXIT_OK
