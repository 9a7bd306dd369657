"""Running the TUI: always attached to a supervisor over its control socket.

``abh3 run CONFIG`` on a terminal starts the supervisor as a child process (headless,
serving the socket) and attaches to it: the buses never share a process with the UI.
Quitting stops the child, so the drives, as ``--headless`` does on SIGTERM. The child
reads a pipe from this process: if this process dies in any way (even ``kill -9``) the
pipe closes and the child stops the drives — no drive runs on without the UI that
started it knowing. ``abh3 tui`` attaches to a supervisor already running; leaving it
only detaches.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from abh3_supervisor.clients.link import Link, LinkError
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.app import STATE_HZ, SupervisorApp, styled
from abh3_supervisor.errors import RunError

log = logging.getLogger("abh3")
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
START_TIMEOUT_S = 60.0  # buses, plugins and the simulator up, the socket served
STOP_TIMEOUT_S = 15.0  # the child's stop path is bounded well below this


UI_NICENESS = 5  # the UI yields the CPU to the buses when both want it


def yield_to_the_buses() -> None:
    """Lower this process's priority: on a small robot computer the UI and the service
    share a few cores, and a late frame matters where a late repaint does not."""
    with contextlib.suppress(OSError):
        os.nice(UI_NICENESS)


async def attach(
    path: Path,
    *,
    owner: bool,
    duration: float | None = None,
    early: Sequence[tuple[int, str]] = (),
) -> int:
    """The app on a supervisor's socket until it quits (or the supervisor goes)."""
    yield_to_the_buses()
    link = await Link.open(path)
    loop = asyncio.get_running_loop()
    try:
        hello = await link.call("hello", name="tui")
        mirror = Mirror.from_hello(hello)
        mirror.apply(await link.call("state"))
        keys = await link.call("keys", taken=SupervisorApp.taken_keys())
        app = SupervisorApp(mirror, link, owner=owner, duration=duration, plugin_keys=keys)
        for level, line in early:
            app.pending_log.append(styled(level, line))
        await link.call("subscribe", events=True, state_hz=STATE_HZ)
        for sig in STOP_SIGNALS:
            loop.add_signal_handler(sig, app.exit)
        try:
            await app.run_async()
        finally:
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
    finally:
        await link.close()
    return app.return_code or 0


class ServiceChild:
    """``abh3 run CONFIG --headless`` as a child: its own session (a Ctrl-C in the UI's
    terminal is the UI's to handle), its log in a file beside the socket, and a pipe
    from this process on its stdin whose end tells it to stop."""

    def __init__(self, config: Path, socket: Path, args: Sequence[str]) -> None:
        self.config, self.socket, self.args = config, socket, list(args)
        self.log_path = socket.with_suffix(".log")
        self.proc: asyncio.subprocess.Process | None = None

    async def start(self) -> None:
        self.socket.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
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
                await link.close()
                return True
            if time.monotonic() > deadline:
                raise RunError(f"the supervisor did not serve {self.socket} within 60 s")
            with contextlib.suppress(TimeoutError):  # polling a child: no event to wait on
                await asyncio.wait_for(self.proc.wait(), 0.05)
        return False

    async def stop(self) -> int:
        """SIGTERM, as a service manager would: the child's own stop path stops the drives."""
        proc = self.proc
        if proc is None:
            return 1
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(proc.wait(), STOP_TIMEOUT_S)
            except TimeoutError:
                proc.kill()
                await proc.wait()
        assert proc.returncode is not None
        return proc.returncode

    def log_lines(self) -> list[str]:
        try:
            return self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return []


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
    """`abh3 run CONFIG` on a terminal: the supervisor as a child, the TUI attached."""
    child = ServiceChild(config, socket, args)
    loop = asyncio.get_running_loop()
    stopping = asyncio.Event()
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, stopping.set)
    print(f"abh3: starting the supervisor (log: {child.log_path})", file=sys.stderr)
    code = 0
    try:
        await child.start()
        up = await child.connected(stopping)
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)
        if up:
            early = warnings(child.log_lines())  # e.g. plugins' start-up warnings
            code = await attach(socket, owner=True, duration=duration, early=early)
    finally:
        with contextlib.suppress(ValueError):
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
        child_code = await child.stop()
    lines = child.log_lines()
    stop_from = max((i for i, line in enumerate(lines) if "stopping" in line), default=0)
    for line in lines[stop_from:] if child_code == 0 else lines[-20:]:
        print(line, file=sys.stderr)
    if child_code:
        print(f"abh3: the supervisor ended with exit code {child_code}", file=sys.stderr)
    return code or child_code
