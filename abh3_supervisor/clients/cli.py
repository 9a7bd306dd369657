"""The ``abh3`` command: :func:`main` parses the command line, then runs the subcommand's
handler under its signal handling and turns its errors into exit codes. Each subcommand
(``run``, ``tui``, ``status``, ``estop``, ``enable``/``disable``, ``send``, ``verify``,
``simulate``, ``check``, ``scan``, ``param``, ``commission``, ``fleet``, ``plugins``,
``plugin new``, ``schema``, ``decode``, ``ros2``) is a module of clients/commands/ with its
parser and its handler; the helpers they share are here.

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
from abh3_supervisor.errors import Abh3Error, ConfigError, Interrupted, PartialWrite, RunError
from abh3_supervisor.runtime import signals  # the standard library only: nothing loads early

if TYPE_CHECKING:
    import argparse
    from types import FrameType

    from abh3_supervisor.clients.commands import Handler
    from abh3_supervisor.config import Config
    from abh3_supervisor.plugin_host.host import PluginHost

EXIT_OK, EXIT_RUNTIME, EXIT_USAGE = 0, 1, 2
EXIT_PARTIAL = 4  # abh3 param restore: some values written, then stopped (journal saved)
MAX_SHOWN = 20  # problems printed; the rest are counted (one mistake can repeat 10 000 times)
CONNECT_HELP = "its control socket, or ssh://[user@]host[:port]/path/to.sock on another host"


def _parser() -> argparse.ArgumentParser:
    """``abh3`` and its subcommands, each from its module in clients/commands/ with its
    handler as ``func``."""
    import argparse

    from abh3_supervisor.clients.commands import add_parsers

    p = argparse.ArgumentParser(prog="abh3", description="Supervise ABH3 drives on CAN buses.")
    p.add_argument("--version", action="version", version=f"abh3-supervisor {__version__}")
    add_parsers(p.add_subparsers(dest="cmd", required=True, metavar="COMMAND"))
    return p


def connecting(parser: argparse.ArgumentParser) -> None:
    """A client of a running supervisor: where it serves, and whom to trust as its server."""
    from abh3_supervisor.clients import peer
    from abh3_supervisor.clients.ssh import endpoint

    parser.add_argument("--connect", type=endpoint, metavar="PATH", help=CONNECT_HELP)
    peer.add_option(parser)


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
    """The subcommand's handler (``func``, set by its module in clients/commands/)."""
    if getattr(args, "trust_server_uid", None):
        from abh3_supervisor.clients import peer

        peer.trust(args.trust_server_uid)
    handler: Handler = args.func
    return handler(args, release)


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


def not_terminals() -> list[str]:
    """The TUI draws on stdout and stderr and reads stdin: all three must be terminals."""
    streams = {"stdin": sys.stdin, "stdout": sys.stdout, "stderr": sys.stderr}
    return [name for name, s in streams.items() if s is None or not s.isatty()]


def plugin_host(config: Config) -> PluginHost:
    """The configuration's plugins loaded and their sections checked, as ``run`` and
    ``check`` both do."""
    from abh3_supervisor.plugin_host.host import PluginHost

    return PluginHost(config)
