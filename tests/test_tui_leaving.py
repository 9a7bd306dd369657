"""The TUI process leaving: `abh3 tui` detaches and is gone within 1 s of SIGHUP, SIGTERM
or its terminal going away — whatever Textual is doing — and the service sees it go;
`abh3 run` on a terminal stops its supervisor child when its terminal goes; the exit
codes say when the supervisor went away under the TUI (4)."""

from __future__ import annotations

import asyncio
import fcntl
import os
import select
import signal
import struct
import sys
import tempfile
import termios
import time
from pathlib import Path

import pytest

from abh3_supervisor.clients.tui.run import EXIT_SUPERVISOR_GONE, rotate
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.server import ControlServer
from tests.support.safe_word import assert_demo_stopped
from tests.support.served import no_clients, served
from tests.support.served import wait_for as _wait_for
from tests.support.terminal import in_a_terminal

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
# the pty becomes the process's controlling terminal, as a shell's would be: closing it
# then sends SIGHUP (without this, only reads and writes fail, as under some multiplexers)
AS_CONTROLLING = (
    "import fcntl, os, sys, termios; fcntl.ioctl(0, termios.TIOCSCTTY, 0); "
    "os.execv(sys.executable, [sys.executable, '-m', 'abh3_supervisor', *sys.argv[1:]])"
)


class Terminal:
    """A pseudo-terminal whose screen is read on the running loop, as a terminal would."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 160, 0, 0))
        self.screen = b""
        self.changed = asyncio.Event()
        self.loop = asyncio.get_running_loop()
        self.loop.add_reader(self.master, self._read)

    def _read(self) -> None:
        try:
            data = os.read(self.master, 65536)
        except OSError:  # EIO: nothing holds the other side any more
            data = b""
        if not data:
            self.stop_reading()
        self.screen += data
        self.changed.set()

    async def shows(self, what: bytes, times: int = 1) -> None:
        while self.screen.count(what) < times:
            self.changed.clear()
            await asyncio.wait_for(self.changed.wait(), 60)

    def stop_reading(self) -> None:
        self.loop.remove_reader(self.master)

    async def start(self, *args: str) -> asyncio.subprocess.Process:
        """``python ARGS`` in its own session with this terminal as stdin, stdout, stderr."""
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            *args,
            stdin=self.slave,
            stdout=self.slave,
            stderr=self.slave,
            start_new_session=True,
            cwd=ROOT,
        )
        os.close(self.slave)
        return proc

    def close(self) -> None:
        self.stop_reading()
        os.close(self.master)


WAYS = ["SIGHUP", "SIGTERM", "SIGTERM, terminal not reading", "pty closed", "pty closed, no ctty"]


@pytest.mark.parametrize("way", WAYS)
def test_abh3_tui_detaches_and_exits_within_1_s(way: str) -> None:
    async def check(rt: Runtime, server: ControlServer, path: Path) -> None:
        term = Terminal()
        controlling = way != "pty closed, no ctty"
        command = ["-c", AS_CONTROLLING] if controlling else ["-m", "abh3_supervisor"]
        proc = await term.start(*command, "tui", "--connect", str(path))
        try:
            await term.shows(b"online", 2)
            assert [c.name for c in server.clients] == ["tui1"]
            t0 = time.monotonic()
            if way.startswith("pty closed"):
                term.close()
            else:
                if "not reading" in way:
                    term.stop_reading()  # its output blocks once the pty's buffer is full
                proc.send_signal(getattr(signal, way.split(",")[0]))
            assert await asyncio.wait_for(proc.wait(), 1.0) == 0
            await no_clients(server)
            assert time.monotonic() - t0 < 1.0
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            if not way.startswith("pty closed"):
                term.close()

    served(check)


def test_abh3_tui_exits_4_when_the_supervisor_went_away() -> None:
    async def check(rt: Runtime, server: ControlServer, path: Path) -> None:
        term = Terminal()
        proc = await term.start("-c", AS_CONTROLLING, "tui", "--connect", str(path))
        try:
            await term.shows(b"online", 2)
            for client in list(server.clients):  # a crash: no "bye", the socket just ends
                client.writer.close()
            await term.shows(b"NOT CONNECTED")
            os.write(term.master, b"q")  # nothing to stop from here: leaves without asking
            await term.shows(b"the supervisor went away while attached")  # said, not only 4
            assert await asyncio.wait_for(proc.wait(), 10) == EXIT_SUPERVISOR_GONE
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
            term.close()

    served(check)


def _child_of(pid: int) -> int:
    """The supervisor child `abh3 run` on a terminal started."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes()
        except (OSError, IndexError):
            continue
        if ppid == pid and b"--exit-with-stdin" in cmdline:
            return int(entry.name)
    raise AssertionError(f"no supervisor child of {pid}")


def _drain(fd: int) -> bytes:
    """Everything the terminal shows until the program has gone."""
    out = b""
    while True:
        ready, _, _ = select.select([fd], [], [], 20)
        try:
            data = os.read(fd, 65536) if ready else b""
        except OSError:
            data = b""
        if not data:
            return out
        out += data


def test_abh3_run_exits_4_when_its_supervisor_is_killed_and_keeps_the_last_log() -> None:
    """The supervisor child killed (-9): NOT CONNECTED, no e-stop claimed, q leaves with
    4 and says what happened (it was 247: -9 as a byte). The previous run's log is kept."""
    sock = Path(tempfile.mkdtemp(dir="/tmp")) / "demo.sock"
    sock.with_name(sock.name + ".log").write_text("the run before\n")
    pid, fd = in_a_terminal(["run", "configs/demo.yaml", "--socket", str(sock)])
    try:
        assert sock.with_name(sock.name + ".log.1").read_text() == "the run before\n"
        os.kill(_child_of(pid), signal.SIGKILL)
        screen = b""
        while b"NOT CONNECTED" not in screen:
            ready, _, _ = select.select([fd], [], [], 20)
            assert ready, screen[-500:]
            screen += os.read(fd, 65536)
        os.write(fd, b"e")  # the e-stop cannot be sent: it says so, and what to do
        while b"E-STOP NOT SENT" not in screen:
            ready, _, _ = select.select([fd], [], [], 20)
            assert ready, screen[-500:]
            screen += os.read(fd, 65536)
        assert b"LATCHED" not in screen
        os.write(fd, b"q")
        said = _drain(fd)
        _, status = os.waitpid(pid, 0)
    finally:
        os.close(fd)
    assert os.waitstatus_to_exitcode(status) == EXIT_SUPERVISOR_GONE
    assert b"killed by SIGKILL" in said and b"command-zero timeout" in said


def test_abh3_run_stops_its_supervisor_when_its_terminal_goes(tmp_path: Path) -> None:
    """The pty closed under `abh3 run` (a tmux session killed): the child is told to stop
    as quitting tells it, stops every drive, and the TUI process is gone at once."""
    sock = Path(tempfile.mkdtemp(dir="/tmp")) / "demo.sock"
    record = tmp_path / "run.log"
    pid, fd = in_a_terminal(
        ["run", "configs/demo.yaml", "--socket", str(sock), "--record", str(record)]
    )
    t0 = time.monotonic()
    os.close(fd)
    os.waitpid(pid, 0)
    assert time.monotonic() - t0 < 2.0
    log = sock.with_name(sock.name + ".log")
    _wait_for(lambda: log.read_text().count("stop frame confirmed") == 2, "both stops confirmed")
    _wait_for(lambda: "recorded" in log.read_text(), "the recording closed")
    assert "SIGTERM: stop" in log.read_text()  # told, as quitting tells it
    assert_demo_stopped(record)


def test_the_previous_log_is_kept(tmp_path: Path) -> None:
    log = tmp_path / "demo.log"
    rotate(log)  # none yet: nothing to keep
    log.write_text("first")
    rotate(log)
    log.write_text("second")
    rotate(log)
    assert (tmp_path / "demo.log.1").read_text() == "second" and not log.exists()
