"""``abh3 check``: validate a configuration and print the bus-load plan, or (``--drives``)
compare the drives' CAN settings with the file."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from abh3_supervisor.clients.cli import EXIT_OK, EXIT_RUNTIME, plugin_host, report
from abh3_supervisor.errors import ConfigError

if TYPE_CHECKING:
    from abh3_supervisor.config import Config


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    check = sub.add_parser("check", help="validate a configuration and print the bus-load plan")
    check.add_argument("config", type=Path)
    check.add_argument("--json", action="store_true", help="machine-readable output")
    check.add_argument(
        "--drives",
        action="store_true",
        help="only read each drive's CAN settings on the file's buses and compare them with "
        "the file (nothing is commanded; exit 0 all agree, 1 a mismatch or not verified)",
    )
    check.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.config import load_config

    try:
        config = load_config(args.config)
        if not args.drives:
            plugin_host(config)  # plugin sections are validated exactly as `run` does
    except ConfigError as exc:
        if args.json:  # a reader of the JSON is told too; stderr and exit 2 as ever
            import json

            refused = {"file": str(args.config), "ok": False, "errors": exc.problems}
            print(json.dumps(refused, indent=2))
        raise
    if args.drives:
        from abh3_supervisor.clients.drives import check_drives

        return check_drives(config, args.json)
    return _check(config, args.json)


def _check(config: Config, as_json: bool) -> int:
    import json

    from abh3_supervisor.config.advice import odometry, warnings
    from abh3_supervisor.core.planner import overloads, plan

    plans = plan(config)
    refused = overloads(config, plans)
    advice = warnings(config)
    if as_json:
        print(
            json.dumps(
                {
                    "file": config.file,
                    "ok": not refused,
                    "units": len(config.units),
                    "buses": [p.to_json() for p in plans],
                    "errors": refused,
                    "warnings": advice,
                },
                indent=2,
            )
        )
    else:
        verdict = "" if refused else " OK,"
        print(f"{config.file}:{verdict} {len(config.units)} unit(s) on {len(config.buses)} bus(es)")
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
        for line in odometry(config):  # per robot: its odom's rate and source
            print(line)
        for warning in advice:
            print(f"warning: {warning}")
    report(refused)
    return EXIT_RUNTIME if refused else EXIT_OK
