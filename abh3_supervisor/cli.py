"""The ``abh3`` command: ``run``, ``check``, ``decode``.

Exit codes: 0 success, 1 runtime failure (bus cannot open, internal error, overloaded
plan), 2 a user's mistake in the configuration or the command line.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from abh3_supervisor import __version__
from abh3_supervisor.config import Config, load_config
from abh3_supervisor.errors import Abh3Error, ConfigError, RunError

if TYPE_CHECKING:
    from abh3_supervisor.plugin_host import PluginHost

EXIT_OK, EXIT_RUNTIME, EXIT_USAGE = 0, 1, 2


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="abh3", description="Supervise ABH3 drives on CAN buses.")
    p.add_argument("--version", action="version", version=f"abh3-supervisor {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the drives of a configuration")
    run.add_argument("config", type=Path)
    run.add_argument(
        "--headless",
        action="store_true",
        help="no TUI: log events to stderr (the only mode so far)",
    )
    run.add_argument(
        "--duration",
        type=_positive,
        metavar="S",
        help="stop after S seconds (default: run until Ctrl-C/SIGTERM)",
    )
    run.add_argument(
        "--record",
        type=Path,
        metavar="FILE",
        help="record all bus traffic; format by extension: .log .asc .blf .csv",
    )
    run.add_argument(
        "--status-interval",
        type=float,
        default=5.0,
        metavar="S",
        help="log a status line per unit every S seconds (0: off; default 5)",
    )
    run.add_argument("-v", "--verbose", action="store_true", help="debug logging")

    check = sub.add_parser("check", help="validate a configuration and print the bus-load plan")
    check.add_argument("config", type=Path)
    check.add_argument("--json", action="store_true", help="machine-readable output")

    dec = sub.add_parser("decode", help="decode a recording made with --record")
    dec.add_argument("file", type=Path)
    dec.add_argument("--config", type=Path, help="name units and pick protocol generations")
    dec.add_argument("--json", action="store_true", help="one JSON object per frame")
    return p


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError("must be more than 0")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if getattr(args, "verbose", False) else logging.INFO,
        format="%(asctime)s.%(msecs)03d %(levelname)-7s %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
    )
    try:
        if args.cmd == "check":
            config = load_config(args.config)
            _plugins(config)  # plugin sections are validated like the core's
            return _check(config, args.json)
        if args.cmd == "decode":
            from abh3_supervisor.decoding import decode_file

            known = load_config(args.config) if args.config else None
            for out in decode_file(args.file, known, args.json):
                print(out)
            return EXIT_OK
        return _run(args)
    except ConfigError as exc:
        for problem in exc.problems:
            print(f"error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    except RunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    except Abh3Error as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # `abh3 decode f.log | head`
        return EXIT_OK


def _run(args: argparse.Namespace) -> int:
    from abh3_supervisor.headless import run_headless

    config = load_config(args.config)
    plugins = _plugins(config)
    if not args.headless and sys.stdin.isatty() and sys.stdout.isatty():
        from abh3_supervisor.tui.app import run_tui

        return asyncio.run(
            run_tui(config, record=args.record, plugins=plugins, duration=args.duration)
        )
    return asyncio.run(
        run_headless(
            config,
            duration=args.duration,
            record=args.record,
            status_interval=args.status_interval,
            plugins=plugins,
        )
    )


def _plugins(config: Config) -> PluginHost:
    from abh3_supervisor.plugin_host import PluginHost

    return PluginHost(config)


def _check(config: Config, as_json: bool) -> int:
    from abh3_supervisor.planner import plan

    plans = plan(config)
    if as_json:
        print(
            json.dumps(
                {
                    "file": config.file,
                    "units": len(config.units),
                    "buses": [p.to_json() for p in plans],
                },
                indent=2,
            )
        )
    else:
        print(f"{config.file}: OK, {len(config.units)} unit(s) on {len(config.buses)} bus(es)")
        for p in plans:
            print(
                f"bus {p.bus}: {p.bitrate} bit/s, {p.frames_per_s:.0f} frames/s, "
                f"load {p.load_percent:.1f} % expected, {p.worst_load_percent:.1f} % worst case"
            )
            for u in p.units:
                print(
                    f"  {u.unit}: {u.exchanges_per_s:g} DP0 exchanges/s, {u.polls_per_s:g} "
                    f"status polls/s, {u.frames_per_s:.0f} frames/s, {u.bits_per_s:.0f} bit/s"
                )
            if p.warning:
                print(f"  warning: {p.warning}")
    return EXIT_RUNTIME if any(p.worst_load_percent > 100 for p in plans) else EXIT_OK
