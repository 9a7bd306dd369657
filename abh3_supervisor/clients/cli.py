"""The ``abh3`` command: ``run``, ``tui``, ``fleet``, ``simulate``, ``check``, ``status``,
``send``, ``estop``, ``verify``, ``scan``, ``param``, ``commission``, ``decode``, ``schema``,
``plugins``, ``plugin new``.

Exit codes: 0 success, 1 runtime failure (bus cannot open, internal error, overloaded
plan), 2 a user's mistake in the configuration or the command line, 3 a stop the drives did
not confirm (``run``), 4 ``abh3 tui``/``abh3 run`` on a terminal: the supervisor went away
while attached, or ``abh3 param restore`` stopped part way (journal saved), 5 a recording
stopped early on a write error (``run``; ``runtime.stopping.final_report``), 6 a plugin
was disabled during the run (``run``), 128 + N stopped by signal N before anything was
started. The README lists them.
"""

from __future__ import annotations

# Only what is needed to catch signals is imported here: the rest (asyncio, YAML, the
# configuration, ~0.1 s) loads after main() has its handlers in place.
import contextlib
import functools
import logging
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING

from abh3_supervisor import __version__
from abh3_supervisor.clients.argtypes import endpoint, positive
from abh3_supervisor.errors import Abh3Error, ConfigError, Interrupted, PartialWrite, RunError
from abh3_supervisor.runtime import signals  # the standard library only: nothing loads early

if TYPE_CHECKING:
    import argparse
    from types import FrameType

    from abh3_supervisor.config import Config
    from abh3_supervisor.plugin_host.host import PluginHost
    from abh3_supervisor.service.server import ServiceOptions

EXIT_OK, EXIT_RUNTIME, EXIT_USAGE = 0, 1, 2
EXIT_PARTIAL = 4  # abh3 param restore: some values written, then stopped (journal saved)
MAX_SHOWN = 20  # problems printed; the rest are counted (one mistake can repeat 10 000 times)
log = logging.getLogger("abh3")
CONNECT_HELP = "its control socket, or ssh://[user@]host[:port]/path/to.sock on another host"


def _parser() -> argparse.ArgumentParser:
    import argparse
    from pathlib import Path

    p = argparse.ArgumentParser(prog="abh3", description="Supervise ABH3 drives on CAN buses.")
    p.add_argument("--version", action="version", version=f"abh3-supervisor {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

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

    tui = sub.add_parser("tui", help="attach the terminal UI to a running supervisor")
    _connecting(tui)

    status = sub.add_parser("status", help="the state of a running supervisor (exit 0: all online)")
    _connecting(status)
    status.add_argument("--json", action="store_true", help="the whole state as JSON")

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
    _connecting(estop)

    for verb, what in (("enable", "on"), ("disable", "off")):
        robot_switch = sub.add_parser(
            verb,
            help=f"switch a running supervisor's robot {what}: SERVO and START of every wheel "
            "axis of its drives, as one act",
            description="Switch SERVO and START of every wheel axis of every drive of each "
            f"ROBOT (or of the robot of a unit named) {what}, as one act: refused whole, naming "
            "the drive, when one cannot take it."
            + (
                " Exit 0 once every drive reports it on; 1 naming the drive that did not "
                "follow within 0.5 s."
                if verb == "enable"
                else " Axes that drive no wheel are never switched on."
            ),
        )
        robot_switch.add_argument("robots", nargs="+", metavar="ROBOT")
        _connecting(robot_switch)

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
    _connecting(send)

    verify = sub.add_parser(
        "verify",
        help="a running supervisor compares drives' CAN settings with its file again",
        description="Ask a running supervisor to read the drives' CAN settings again and "
        "compare them with its YAML; a unit that verify: refuse holds is released when they "
        "now agree (its startup: commands run then). Exit 0 when every one agrees.",
    )
    verify.add_argument("units", nargs="+", metavar="UNIT")
    _connecting(verify)
    verify.add_argument("--json", action="store_true", help="the results as JSON")

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
    check = sub.add_parser("check", help="validate a configuration and print the bus-load plan")
    check.add_argument("config", type=Path)
    check.add_argument("--json", action="store_true", help="machine-readable output")
    check.add_argument(
        "--drives",
        action="store_true",
        help="only read each drive's CAN settings on the file's buses and compare them with "
        "the file (nothing is commanded; exit 0 all agree, 1 a mismatch or not verified)",
    )

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
    from abh3_supervisor.clients.param import add_parser as add_param_parser

    add_param_parser(sub)
    from abh3_supervisor.clients.commission import add_parser as add_commission_parser

    add_commission_parser(sub)
    from abh3_supervisor.clients.fleet.run import add_parser as add_fleet_parser

    add_fleet_parser(sub)
    plugins = sub.add_parser(
        "plugins",
        help="the installed plugins: version, API version, hooks; with CONFIG, which it enables",
    )
    plugins.add_argument("config", type=Path, nargs="?", metavar="CONFIG")
    plugins.add_argument("--json", action="store_true", help="machine-readable output")
    plugin = sub.add_parser("plugin", help="plugin authors' tools").add_subparsers(
        dest="plugin", required=True
    )
    new = plugin.add_parser(
        "new",
        help="write a pip-installable plugin package: an example hook, its test, pyproject",
    )
    new.add_argument("name", help="the plugin's name in the YAML (lowercase, digits, _)")
    new.add_argument(
        "--dir", type=Path, default=Path("."), metavar="D", help="create it in D (default: .)"
    )
    schema = sub.add_parser(
        "schema", help="print the configuration's JSON Schema (core and installed plugins)"
    )
    schema.add_argument("--output", "-o", type=Path, metavar="FILE", help="write it here")

    dec = sub.add_parser("decode", help="decode a recording made with --record")
    dec.add_argument("file", type=Path)
    dec.add_argument("--config", type=Path, help="name units and pick protocol generations")
    dec.add_argument("--json", action="store_true", help="one JSON object per frame")

    ros2 = sub.add_parser("ros2", help="ROS 2 helpers").add_subparsers(dest="ros2", required=True)
    build = ros2.add_parser(
        "build-interface",
        help="build abh3_can_interface with cmake (no colcon) from a sourced ROS 2 or the wheels",
    )
    build.add_argument("--prefix", type=Path, required=True, help="install it here")
    build.add_argument(
        "--distro",
        choices=["kilted", "jazzy"],
        help="use this distro's wheels from the package registry (default: a sourced "
        "ROS 2 if there is one, else kilted)",
    )
    return p


def _connecting(parser: argparse.ArgumentParser) -> None:
    """A client of a running supervisor: where it serves, and whom to trust as its server."""
    from abh3_supervisor.clients import peer
    from abh3_supervisor.clients.ssh import endpoint

    parser.add_argument("--connect", type=endpoint, metavar="PATH", help=CONNECT_HELP)
    peer.add_option(parser)


def _address(text: str) -> int:
    import argparse

    if not text.isdigit() or not 0 <= int(text) <= 253:
        raise argparse.ArgumentTypeError(f"'{text}' is not an address 0–253")
    return int(text)


def run() -> None:
    """The ``abh3`` command as a process: :func:`main`, then the exit, which no late stop
    signal changes (docs/signals.md)."""
    raise SystemExit(main(exiting=True))


def main(argv: Sequence[str] | None = None, *, exiting: bool = False) -> int:
    """``exiting``: the process ends when this returns — the stop signals are left
    ignored rather than given back to their defaults (:func:`run`)."""
    command = ""
    try:
        with _interruptible(exiting) as release:
            args = _parser().parse_args(argv)
            command = args.cmd
            logging.basicConfig(
                level=logging.DEBUG if getattr(args, "verbose", False) else logging.INFO,
                format="%(asctime)s.%(msecs)03d %(levelname)-7s %(message)s",
                datefmt="%H:%M:%S",
                stream=sys.stderr,
            )
            return _command(args, release)
    except Interrupted as exc:
        name = signals.name(exc.signum)
        if exc.ending:  # the command's own way out had run: nothing was left to stop
            when = " while exiting, after its way out"
        else:
            when = " while starting; no drive was started" if command == "run" else ""
        print(f"abh3: stopped by {name}{when}", file=sys.stderr)
        return 128 + exc.signum
    except ConfigError as exc:
        report(exc.problems)
        return EXIT_USAGE
    except PartialWrite as exc:
        with contextlib.suppress(OSError):  # the reader may be gone: the code still says it
            print(f"error: {exc}", file=sys.stderr)
        return EXIT_PARTIAL
    except RunError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_RUNTIME
    except Abh3Error as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except BrokenPipeError:  # `abh3 decode f.log | head`
        return EXIT_OK


def _command(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.config import load_config

    if getattr(args, "trust_server_uid", None):
        from abh3_supervisor.clients import peer

        peer.trust(args.trust_server_uid)

    if args.cmd == "tui":
        return _tui_attached(args, release)
    if args.cmd == "fleet":
        return _fleet(args, release)
    if args.cmd == "verify":
        from abh3_supervisor.clients import control
        from abh3_supervisor.clients.drives import verify_running

        return verify_running(control.find_socket(args.connect), args.units, args.json)
    if args.cmd in ("enable", "disable"):
        from abh3_supervisor.clients import control

        path = control.find_socket(args.connect)
        return control.enable(path, args.robots, on=args.cmd == "enable")
    if args.cmd in ("status", "send", "estop"):
        from abh3_supervisor.clients import control as client

        if args.cmd == "estop" and not args.clear:  # every one served, where not told which
            return client.estop_every(client.find_sockets(args.connect))
        path = client.find_socket(args.connect)
        if args.cmd == "status":
            return client.status(path, args.json)
        if args.cmd == "estop":
            return client.estop(path, clear=True)
        return client.send(path, args.text, args.unit, every=args.all, hold=args.hold)
    if args.cmd == "check":
        try:
            config = load_config(args.config)
            if not args.drives:
                _plugins(config)  # plugin sections are validated exactly as `run` does
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
    if args.cmd == "simulate":
        return _simulate(args, release)
    if args.cmd == "scan":
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
    if args.cmd == "param":
        from abh3_supervisor.clients import param

        return param.run(args)
    if args.cmd == "commission":
        from abh3_supervisor.clients import commission

        return commission.run(args)
    if args.cmd == "plugins":
        from abh3_supervisor.clients.plugins import plugins_command

        return plugins_command(args.config, args.json)
    if args.cmd == "plugin":
        from abh3_supervisor.clients.plugin_template import new_plugin

        print(f"wrote {new_plugin(args.name, args.dir)}")
        return EXIT_OK
    if args.cmd == "schema":
        from abh3_supervisor.clients.schema import schema_text

        if args.output is None:
            sys.stdout.write(schema_text())
            return EXIT_OK
        try:
            args.output.write_text(schema_text(), encoding="utf-8")
        except OSError as exc:
            raise Abh3Error(f"--output {args.output}: cannot write: {exc.strerror}") from exc
        return EXIT_OK
    if args.cmd == "ros2":
        from abh3_supervisor.clients import ros2_interface

        try:
            return ros2_interface.command(args.prefix, args.distro)
        except ros2_interface.BuildError as exc:
            raise RunError(str(exc)) from None
    if args.cmd == "decode":
        from abh3_supervisor.clients.decode import decode_file

        known = load_config(args.config) if args.config else None
        for out in decode_file(args.file, known, args.json):
            print(out)
        return EXIT_OK
    return _run(args, release)


def _simulate(args: argparse.Namespace, release: Callable[[], None]) -> int:
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


def report(problems: Sequence[str]) -> None:
    """Print problems on stderr, at most MAX_SHOWN of them."""
    for problem in problems[:MAX_SHOWN]:
        print(f"error: {problem}", file=sys.stderr)
    if len(problems) > MAX_SHOWN:
        print(f"error: and {len(problems) - MAX_SHOWN} more", file=sys.stderr)


@contextlib.contextmanager
def _interruptible(exiting: bool = False) -> Iterator[Callable[[], None]]:
    """Until the runtime installs its own handlers, a stop signal ends the program at once.

    Python's default turns SIGINT into a KeyboardInterrupt traceback, and the runtime's
    loop handlers cannot interrupt a bus or a recording that blocks while it opens.
    Yields a function that gives the previous handlers back early (for the TUI). At the
    end they are given back, or, when the process then ends (``exiting``), the stop
    signals are ignored: a second Ctrl-C after a quick way out came while the interpreter
    wound down and ended the process by SIGINT, not with the stop's exit code.
    """
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None  # signals are only ever delivered to the main thread
        return
    signals.ignore_harmless()
    saved = signals.catch(functools.partial(_interrupt, signals.took_over()))

    def release() -> None:
        signals.restore(saved)

    try:
        yield release
    finally:
        if exiting:
            signals.ignore_stops()
        else:
            release()


def _interrupt(took_over: int, signum: int, frame: FrameType | None) -> None:
    """``took_over``: :func:`signals.took_over` when this handler was installed; more now,
    and the signal came after a loop's handlers had done their work and given this one
    back (a run that ended by itself, as its interpreter winds down)."""
    if _in_machinery(frame):
        # raised here it could leave the event loop half built (a traceback at exit): ask
        # again in a moment, when our own code runs or the runtime's handler has taken over
        threading.Timer(0.01, os.kill, (os.getpid(), signum)).start()
        return
    raise Interrupted(signum, ending=signals.took_over() != took_over)


_STDLIB = os.path.dirname(os.__file__)


def _in_machinery(frame: FrameType | None) -> bool:
    """Is the innermost code that is not plain library code the event loop's?"""
    # where a raised signal would corrupt state: the event loop's code and what it uses
    machinery = tuple(
        os.path.dirname(module.__file__) if name == "asyncio" else module.__file__
        for name in ("asyncio", "selectors", "threading")
        if (module := sys.modules.get(name)) is not None and module.__file__
    )
    while frame is not None:
        name = frame.f_code.co_filename
        if name.startswith(machinery):
            return True
        library = name.startswith("<") or (name.startswith(_STDLIB) and "-packages" not in name)
        if not library:  # ours, python-can, PyYAML, a plugin: safe to raise through
            return False
        frame = frame.f_back
    return False


def _run(args: argparse.Namespace, release: Callable[[], None]) -> int:
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
    plugins = _plugins(config)
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
        redirected = _not_terminals()
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


def _not_terminals() -> list[str]:
    """The TUI draws on stdout and stderr and reads stdin: all three must be terminals."""
    streams = {"stdin": sys.stdin, "stdout": sys.stdout, "stderr": sys.stderr}
    return [name for name, s in streams.items() if s is None or not s.isatty()]


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


def _tui_attached(args: argparse.Namespace, release: Callable[[], None]) -> int:
    import asyncio

    from abh3_supervisor.clients.control import find_socket
    from abh3_supervisor.clients.tui.run import attach

    if redirected := _not_terminals():
        raise RunError(f"{'/'.join(redirected)} not a terminal: the TUI needs one")
    path = find_socket(args.connect)
    release()
    return asyncio.run(attach(path, owner=False))


def _fleet(args: argparse.Namespace, release: Callable[[], None]) -> int:
    from abh3_supervisor.clients.fleet.run import options, run

    opts = options(args)  # a mistake in the options is said (exit 2) before anything else
    release()  # the view handles its own keys and signals
    return run(args, opts, _not_terminals)


def _service(args: argparse.Namespace) -> ServiceOptions | None:
    from abh3_supervisor.service.paths import default_socket
    from abh3_supervisor.service.server import ServiceOptions

    if args.no_socket:
        return None
    path = args.socket or default_socket(str(args.config))
    return ServiceOptions(path, args.socket_group, args.read_only_socket)


def _plugins(config: Config) -> PluginHost:
    from abh3_supervisor.plugin_host.host import PluginHost

    return PluginHost(config)


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
