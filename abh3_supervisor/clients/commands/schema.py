"""``abh3 schema``: the configuration's JSON Schema (core and installed plugins)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from abh3_supervisor.clients.cli import EXIT_OK
from abh3_supervisor.errors import Abh3Error


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    schema = sub.add_parser(
        "schema", help="print the configuration's JSON Schema (core and installed plugins)"
    )
    schema.add_argument("--output", "-o", type=Path, metavar="FILE", help="write it here")
    schema.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.schema import schema_text

    if args.output is None:
        sys.stdout.write(schema_text())
        return EXIT_OK
    try:
        args.output.write_text(schema_text(), encoding="utf-8")
    except OSError as exc:
        raise Abh3Error(f"--output {args.output}: cannot write: {exc.strerror}") from exc
    return EXIT_OK
