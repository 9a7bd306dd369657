"""``abh3 simulate``: a file's simulated drives as a process of their own on its shared bus
(docs/simulator.md)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from abh3_supervisor.clients.argtypes import positive


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sim = sub.add_parser(
        "simulate",
        help="run a file's simulated drives as a process of their own on its shared bus",
        description="Run the simulated drives of CONFIG's `simulate:` buses on the bus the "
        "file names (udp_multicast or a SocketCAN vcan), where `abh3 run`, `tui`, "
        "`commission`, `param` and `scan` reach them as real drives. Standard input takes "
        "`power off|on UNIT`, `unplug|plug UNIT`, `status`, `help` (docs/simulator.md).",
    )
    sim.add_argument("config", type=Path)
    sim.add_argument("--bus", action="append", default=[], help="only this bus (repeatable)")
    sim.add_argument("--trace", type=Path, help="what the drives do, as JSON lines")
    sim.add_argument("--record", type=Path, help="the frames they hear and send (.log, .asc…)")
    sim.add_argument("--duration", type=positive, metavar="S", help="stop after S seconds")
    sim.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    import asyncio

    from abh3_supervisor.config import load_config
    from abh3_supervisor.runtime.simulating import simulate, simulated_buses

    if args.record is not None:
        from abh3_supervisor.runtime.recorder import check_format

        check_format(args.record)
    config = load_config(args.config)
    buses = simulated_buses(config, args.bus)
    running = simulate(config, buses, trace=args.trace, record=args.record, duration=args.duration)
    try:
        return asyncio.run(running)
    finally:
        running.close()
