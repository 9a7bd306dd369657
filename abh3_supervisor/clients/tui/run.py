"""Running the TUI: always attached to a supervisor over its control socket.

``abh3 run CONFIG`` on a terminal starts the supervisor as a child process (headless,
serving the socket) and attaches to it: the buses never share a process with the UI.
Quitting stops the child, so the drives, as ``--headless`` does on SIGTERM. The child
reads a pipe from this process: if this process dies in any way (even ``kill -9``) the
pipe closes and the child stops the drives — no drive runs on without the UI that
started it knowing. ``abh3 tui`` attaches to a supervisor already running; leaving it
only detaches.

Exit codes (README, "The terminal UI"): 0 the operator quit, or a signal or the terminal
going away ended it; 1 it could not attach or could not finish; the child's own 1, 2 or
3 (``abh3 run``); 4 the supervisor went away while attached (killed, crashed, or stopped
by someone else): what the drives do was not seen from here.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import select
import signal
import sys
import termios
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType, TracebackType
from typing import Any

from abh3_supervisor.clients import peer
from abh3_supervisor.clients.link import Link, LinkError
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.ssh import Endpoint
from abh3_supervisor.clients.tui.app import STATE_HZ, SupervisorApp, styled
from abh3_supervisor.errors import Abh3Error, RunError
from abh3_supervisor.runtime import priority, signals
from abh3_supervisor.service import paths

log = logging.getLogger("abh3")
START_TIMEOUT_S = 60.0  # buses, plugins and the simulator up, the socket served
STOP_TIMEOUT_S = 15.0  # the child's stop path is bounded well below this
DETACH_S = 0.6  # `abh3 tui` is gone within this of a signal or its terminal going away
EXIT_RUNTIME = 1
EXIT_SUPERVISOR_GONE = 4  # the supervisor went away while this TUI was attached


UI_NICENESS = 5  # the UI yields the CPU to the buses when both want it


def yield_to_the_buses() -> None:
    """Lower this process's priority: on a small robot computer the UI and the service
    share a few cores, and a late frame matters where a late repaint does not. A UI
    started from a real-time process (a benchmark, a supervisor's plugin) drops that too:
    only the bus loop runs real-time (runtime/priority.py)."""
    priority.normal()
    with contextlib.suppress(OSError):
        os.nice(UI_NICENESS)


def tell(line: str) -> None:
    """A line on stderr, if the terminal is still there to take it."""
    with contextlib.suppress(OSError):
        print(line, file=sys.stderr)


class Departure:
    """Leaving on SIGHUP, SIGTERM, SIGINT or the terminal going away, whatever state the
    UI is in, and ending the process if the UI cannot: within ``DETACH_S`` once the
    terminal is gone (nothing can be shown any more), within ``patience`` otherwise.

    Textual cannot be relied on here: its output thread dies on a terminal that is gone,
    after which the event loop blocks on that thread's full queue (it blocks the same way
    on a terminal that stops reading), and it reads a closed pseudo-terminal as an endless
    end-of-file. So the signal handlers are Python's own (they run while the loop is
    blocked), a thread waits for the terminal to hang up (``poll`` reports POLLHUP even
    unasked), and that thread ends the process at the deadline. The actions registered
    with :meth:`on_leave` run at once, in whichever thread noticed: they must be
    idempotent and safe from any thread.
    """

    def __init__(self, patience: float, forced_code: int) -> None:
        self.patience, self.forced_code = patience, forced_code
        self.why: str | None = None
        self._actions: list[Callable[[], object]] = []
        self._saved: dict[int, object] = {}
        self._wake_r, self._wake_w = os.pipe()
        self._ttys = [fd for fd in (0, 1, 2) if os.isatty(fd)]
        self._modes = {fd: _modes(fd) for fd in self._ttys}

    def __enter__(self) -> Departure:
        self._saved = signals.catch(self._signalled)  # all that would end us: docs/signals.md
        threading.Thread(target=self._watch, name="abh3-departure", daemon=True).start()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        signals.restore(self._saved)
        if self.why is None:
            self.why = ""  # done: the watcher ends (a deadline, once leaving, stays armed)
            os.write(self._wake_w, b"x")

    def on_leave(self, action: Callable[[], object]) -> None:
        self._actions.append(action)
        if self.why:  # already leaving
            action()

    def leave(self, why: str) -> None:
        if self.why is not None:
            return
        self.why = why
        os.write(self._wake_w, b"x")  # the deadline runs from now
        for action in list(self._actions):
            action()

    def _signalled(self, signum: int, frame: FrameType | None) -> None:
        self.leave(signals.name(signum))

    def _watch(self) -> None:
        terminal = select.poll()
        for fd in self._ttys:
            terminal.register(fd, 0)  # nothing asked: only a hangup or an error wakes it
        both = select.poll()
        for fd in (*self._ttys, self._wake_r):
            both.register(fd, select.POLLIN if fd == self._wake_r else 0)
        both.poll()
        gone = bool(terminal.poll(0))
        if gone:
            self.leave("the terminal went away")
        if self.why:  # leaving (else finished without): the UI has until the deadline
            time.sleep(DETACH_S if gone else self.patience)
            self._force()

    def _force(self) -> None:
        """The UI could not finish in time: give the terminal its modes back if it is still
        there, and end. The socket closes with the process, so the service sees it go."""
        for fd, modes in self._modes.items():
            if modes is not None:
                with contextlib.suppress(termios.error, OSError):
                    termios.tcsetattr(fd, termios.TCSANOW, modes)
        os._exit(self.forced_code)


def _modes(fd: int) -> list[Any] | None:
    try:
        return termios.tcgetattr(fd)
    except termios.error:
        return None


async def attach(
    path: Endpoint,
    *,
    owner: bool,
    duration: float | None = None,
    early: Sequence[tuple[int, str]] = (),
    leaving: Departure | None = None,
    server_pid: int | None = None,
) -> int:
    """The app on a supervisor's socket until it quits, a signal or the terminal going
    away ends it (detaching at once), or the supervisor goes. ``server_pid``: the
    supervisor this process started; a socket served by any other process is refused."""
    yield_to_the_buses()
    with contextlib.ExitStack() as stack:
        if leaving is None:
            leaving = stack.enter_context(Departure(DETACH_S, forced_code=0))
        link = await Link.open(path)
        loop = asyncio.get_running_loop()
        try:
            if server_pid is not None:
                not_ours(link, server_pid)
            hello = await link.call("hello", name="tui")
            mirror = Mirror.from_hello(hello)
            mirror.apply(await link.call("state"))
            keys = await link.call("keys", taken=SupervisorApp.taken_keys())
            shows = f"{hello.get('config_path') or hello.get('config')} · {path}"
            app = SupervisorApp(
                mirror, link, owner=owner, duration=duration, plugin_keys=keys, shows=shows
            )
            for level, line in early:
                app.pending_log.append(styled(level, line))
            await link.call("subscribe", events=True, state_hz=STATE_HZ)
            leaving.on_leave(link.detach_now)
            leaving.on_leave(lambda: loop.call_soon_threadsafe(app.exit))
            if leaving.why is None:
                await app.run_async()
        finally:
            await link.close()
    if leaving.why:  # detached on purpose (its own detach ends the link, not the service)
        return 0
    if app.gone is None:
        return app.return_code or 0
    if not owner:  # `abh3 run` says it itself, with how its child ended
        print(
            f"abh3 tui: the supervisor went away while attached ({app.gone}; exit code "
            f"{EXIT_SUPERVISOR_GONE})",
            file=sys.stderr,
        )
    return EXIT_SUPERVISOR_GONE


def not_ours(link: Link, pid: int) -> None:
    """:class:`Abh3Error` unless the process serving ``link`` is ``pid`` (as far as the
    OS says): `abh3 run` shows, and commands through, only the supervisor it started."""
    found = peer.credentials(link.writer.get_extra_info("socket"))
    if found is not None and found[0] != pid:
        raise Abh3Error(refusal(link.path, f"process {found[0]}"))


def refusal(socket: Endpoint, who: str) -> str:
    return (
        f"control socket {socket}: {who} serves it already, not the supervisor this "
        "`abh3 run` starts; this TUI shows and commands only its own: stop that one, attach "
        f"to it with `abh3 tui --connect {socket}`, or give this run --socket PATH"
    )


class ServiceChild:
    """``abh3 run CONFIG --headless`` as a child: its own session (a Ctrl-C in the UI's
    terminal is the UI's to handle), its log in a file beside the socket, and a pipe
    from this process on its stdin whose end tells it to stop."""

    def __init__(self, config: Path, socket: Path, args: Sequence[str]) -> None:
        self.config, self.socket, self.args = config, socket, list(args)
        # demo.sock → demo.sock.log: never the name a recording is given (`--record demo.log`)
        self.log_path = socket.with_name(socket.name + ".log")
        self.proc: asyncio.subprocess.Process | None = None
        self.terminated = self.killed = False

    async def start(self) -> None:
        # made here for the log, as the child would make it (with --socket-group, the
        # group's): the child uses a directory it finds as it is, never chmodding it
        args = self.args
        group = args[args.index("--socket-group") + 1] if "--socket-group" in args else None
        paths.prepare_directory(self.socket, paths.group_id(group))
        rotate(self.log_path)
        with self.log_path.open("wb") as out:
            self.proc = await asyncio.create_subprocess_exec(
                sys.executable,
                "-m",
                "abh3_supervisor",
                "run",
                str(self.config),
                "--headless",
                "--socket",
                str(self.socket),
                "--status-interval",
                "0",
                "--exit-with-stdin",
                *self.args,
                stdin=asyncio.subprocess.PIPE,
                stdout=out,
                stderr=out,
                start_new_session=True,
            )

    async def connected(self, stopping: asyncio.Event) -> bool:
        """Until the socket answers; False when the child ended first (or a signal)."""
        assert self.proc is not None
        deadline = time.monotonic() + START_TIMEOUT_S
        while self.proc.returncode is None and not stopping.is_set():
            with contextlib.suppress(LinkError):
                link = await Link.open(self.socket, timeout=1.0)
                try:
                    not_ours(link, self.proc.pid)  # another one took the path meanwhile
                finally:
                    await link.close()
                return True
            if time.monotonic() > deadline:
                raise RunError(f"the supervisor did not serve {self.socket} within 60 s")
            with contextlib.suppress(TimeoutError):  # polling a child: no event to wait on
                await asyncio.wait_for(self.proc.wait(), 0.05)
        return False

    def terminate(self) -> None:
        """SIGTERM, as a service manager would: the child's own stop path stops the drives.
        Once only: a second one could land after the child gave its handlers back. Safe
        from a signal handler or another thread."""
        if self.proc is not None and self.proc.returncode is None and not self.terminated:
            self.terminated = True
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.proc.pid, signal.SIGTERM)

    async def stop(self) -> int:
        """Terminate the child, wait for its stop path, and give its exit code (negative: the
        signal that ended it)."""
        proc = self.proc
        if proc is None:
            return 1
        self.terminate()
        try:
            await asyncio.wait_for(proc.wait(), STOP_TIMEOUT_S)
        except TimeoutError:
            self.killed = True
            proc.kill()
            await proc.wait()
        assert proc.returncode is not None
        return proc.returncode

    def log_lines(self) -> list[str]:
        try:
            return self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return []


def rotate(log_path: Path) -> None:
    """Keep the previous run's log (``.log.1``): after a crash it is the one that matters."""
    with contextlib.suppress(FileNotFoundError):
        log_path.replace(log_path.with_name(log_path.name + ".1"))


LINE = re.compile(r"\d\d:\d\d:\d\d\.\d{3} (?P<level>[A-Z]+) +(?P<text>.*)")


def warnings(lines: Sequence[str]) -> list[tuple[int, str]]:
    """The warnings and errors of the child's log (its lines before the socket served)."""
    found = []
    for line in lines:
        m = LINE.fullmatch(line)
        level = logging.getLevelName(m["level"]) if m else logging.WARNING
        if isinstance(level, int) and level >= logging.WARNING:
            found.append((level, m["text"] if m else line))
    return found


async def run_tui(
    config: Path, socket: Path, args: Sequence[str], duration: float | None = None
) -> int:
    """`abh3 run CONFIG` on a terminal: the supervisor as a child, the TUI attached. A
    signal or the terminal going away stops the child as quitting does."""
    if paths.served(socket):  # refused before the TUI opens, nothing started
        raise Abh3Error(refusal(socket, "another supervisor"))
    child = ServiceChild(config, socket, args)
    loop = asyncio.get_running_loop()
    stopping = asyncio.Event()
    tell(f"abh3: starting the supervisor (log: {child.log_path})")
    code = 0
    # with the terminal still there, leaving waits for the child's stop to show its end
    with Departure(STOP_TIMEOUT_S + 5.0, forced_code=EXIT_RUNTIME) as leaving:
        leaving.on_leave(lambda: loop.call_soon_threadsafe(stopping.set))
        leaving.on_leave(child.terminate)  # the drives stop now, whatever the UI does
        try:
            await child.start()
            if await child.connected(stopping):
                early = warnings(child.log_lines())  # e.g. plugins' start-up warnings
                assert child.proc is not None
                code = await attach(
                    socket,
                    owner=True,
                    duration=duration,
                    early=early,
                    leaving=leaving,
                    server_pid=child.proc.pid,
                )
        finally:
            child_code = await child.stop()
        lines = child.log_lines()
        stop_from = max((i for i, line in enumerate(lines) if "stopping" in line), default=0)
        for line in lines[stop_from:] if child_code == 0 else lines[-20:]:
            tell(line)
        return outcome(child, child_code, code)


def outcome(child: ServiceChild, child_code: int, code: int) -> int:
    """The exit code of `abh3 run` on a terminal, and a line saying how the child ended
    when that is not the ordinary way."""
    if child_code < 0 and not child.killed:
        name = signals.name(-child_code)
        tell(
            f"abh3: the supervisor was killed by {name} (exit code {EXIT_SUPERVISOR_GONE}): "
            "it sent no stop frames — the drives stop on their own command-zero timeout "
            "once its frames cease; check them"
        )
        return EXIT_SUPERVISOR_GONE
    if child.killed:
        tell(f"abh3: the supervisor did not stop within {STOP_TIMEOUT_S:g} s: killed; check it")
        return EXIT_RUNTIME
    if child_code:
        tell(f"abh3: the supervisor ended with exit code {child_code}")
        return child_code
    if code == EXIT_SUPERVISOR_GONE:
        tell(f"abh3: the supervisor stopped while the TUI was attached (exit code {code})")
    return code
