"""``abh3 run``: the drives of a configuration — headless, or on a terminal with the TUI
attached to the supervisor in a child process."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from abh3_supervisor.clients.argtypes import endpoint, positive
from abh3_supervisor.clients.cli import EXIT_RUNTIME, not_terminals, plugin_host, report
from abh3_supervisor.errors import RunError

if TYPE_CHECKING:
    from abh3_supervisor.config import Config
    from abh3_supervisor.plugin_host.host import PluginHost
    from abh3_supervisor.service.server import ServiceOptions

log = logging.getLogger("abh3")


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    run = sub.add_parser("run", help="run the drives of a configuration")
    run.add_argument("config", type=Path)
    run.add_argument(
        "--headless",
        action="store_true",
        help="no TUI: log events to stderr (the default when stdin, stdout or stderr is "
        "not a terminal)",
    )
    run.add_argument(
        "--duration",
        type=positive,
        metavar="S",
        help="stop after S seconds (default: run until Ctrl-C/SIGTERM)",
    )
    run.add_argument(
        "--record",
        type=Path,
        metavar="FILE",
        help="record all bus traffic; format by extension: .log .asc .blf .csv, or .mcap "
        "(raw frames and decoded values as ROS 2 messages; the mcap extra)",
    )
    run.add_argument(
        "--foxglove",
        type=endpoint,
        metavar="[HOST:]PORT",
        help="serve the .mcap recording's topics live to Foxglove over its WebSocket "
        "protocol (127.0.0.1 unless a host is given; watch only; the foxglove extra); "
        "overrides the file's `foxglove:`",
    )
    run.add_argument(
        "--priority",
        choices=["auto", "realtime", "normal"],
        default="auto",
        help="the bus loop's CPU scheduling: real-time (SCHED_FIFO) where allowed, else "
        "normal (auto, the default); realtime: refuse to start without it",
    )
    run.add_argument(
        "--status-interval",
        type=float,
        default=5.0,
        metavar="S",
        help="log a status line per unit every S seconds (0: off; default 5)",
    )
    run.add_argument(
        "--socket",
        type=Path,
        metavar="PATH",
        help="serve the control socket here (default: $XDG_RUNTIME_DIR/abh3/CONFIG.sock, "
        "else /tmp/abh3-UID/CONFIG.sock)",
    )
    run.add_argument("--no-socket", action="store_true", help="serve no control socket")
    run.add_argument(
        "--socket-group", metavar="GROUP", help="members of GROUP may use the socket too"
    )
    run.add_argument(
        "--read-only-socket",
        type=Path,
        metavar="PATH",
        help="also serve a read-only socket (state and events; no commands)",
    )
    run.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    # the TUI's child: stop when the pipe on stdin from the TUI closes (it quit or died)
    run.add_argument("--exit-with-stdin", action="store_true", help=argparse.SUPPRESS)
    run.set_defaults(func=handle)


def handle(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.config import load_config
    from abh3_supervisor.core.planner import overloads, plan

    if args.record is not None:  # a typo in the name: exit 2, before anything opens
        from abh3_supervisor.runtime.recorder import check_format

        check_format(args.record)
    config = load_config(args.config)
    if args.foxglove is not None:
        import dataclasses

        config = dataclasses.replace(config, foxglove=args.foxglove)
    if config.foxglove is not None:  # the extra missing: exit 2, before anything opens
        from abh3_supervisor.runtime.foxglove_live import check_installed

        check_installed(
            f"--foxglove {args.foxglove}" if args.foxglove else f"{config.file}: foxglove"
        )
    plugins = plugin_host(config)
    if args.record is not None:  # onto a plugin's own file: exit 2, before anything opens
        plugins.refuse_recording_onto_an_output(args.record, config.units)
    plans = plan(config)
    refused = overloads(config, plans)
    if refused:  # the same lines `abh3 check` prints
        report(refused)
        return EXIT_RUNTIME
    for p in plans:
        if p.warning:
            log.warning("bus %s: %s", p.bus, p.warning)
    from abh3_supervisor.config.advice import warnings

    for warning in warnings(config):
        log.warning("%s", warning)
    if args.record is not None:
        from abh3_supervisor.runtime.recording import recording

        log.info("%s", recording(args.record))
    if not args.headless:
        redirected = not_terminals()
        if not redirected:
            return _tui_with_child(args, release)
        print(
            f"abh3: {'/'.join(redirected)} not a terminal: running headless (--headless)",
            file=sys.stderr,
        )
    if args.exit_with_stdin:
        from abh3_supervisor.plugin_host import terminal

        terminal.claim("the TUI that started this supervisor")  # it hands keys over
    from abh3_supervisor.runtime.priority import Priority, bus_priority

    with bus_priority(Priority(args.priority)) as priority:  # before any thread starts
        log.info("%s", priority)
        return _run_headless(args, config, plugins)


def _run_headless(args: argparse.Namespace, config: Config, plugins: PluginHost) -> int:
    import asyncio

    from abh3_supervisor.runtime.headless import run_headless

    running = run_headless(
        config,
        duration=args.duration,
        record=args.record,
        status_interval=args.status_interval,
        plugins=plugins,
        service=_service(args),
        exit_with_stdin=args.exit_with_stdin,
    )
    try:
        code = asyncio.run(running)
    finally:
        running.close()  # a signal before it started: no "never awaited" warning
    left = plugins.leftovers()  # they would hold the interpreter's exit forever
    if left:
        log.error("exiting without waiting for %s (exit code %d)", ", ".join(left), code)
        logging.shutdown()
        with contextlib.suppress(OSError):
            sys.stdout.flush()
        os._exit(code)
    return code


def _tui_with_child(args: argparse.Namespace, release: Callable[[], None]) -> int:
    """`abh3 run` on a terminal: the supervisor in a child process, the TUI attached."""
    import asyncio

    from abh3_supervisor.clients.tui.run import run_tui
    from abh3_supervisor.service.paths import default_socket

    if args.no_socket:
        raise RunError("the TUI attaches through the control socket: --no-socket needs --headless")
    passed: list[str] = []
    for flag, value in (
        ("--priority", args.priority),
        ("--record", args.record),
        ("--foxglove", args.foxglove),
        ("--socket-group", args.socket_group),
        ("--read-only-socket", args.read_only_socket),
    ):
        if value is not None:
            passed += [flag, str(value)]
    if args.verbose:
        passed.append("--verbose")
    socket = args.socket or default_socket(str(args.config))
    release()  # the TUI handles its own keys and signals
    return asyncio.run(run_tui(args.config, socket, passed, duration=args.duration))


def _service(args: argparse.Namespace) -> ServiceOptions | None:
    from abh3_supervisor.service.paths import default_socket
    from abh3_supervisor.service.server import ServiceOptions

    if args.no_socket:
        return None
    path = args.socket or default_socket(str(args.config))
    return ServiceOptions(path, args.socket_group, args.read_only_socket)
