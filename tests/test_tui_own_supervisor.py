"""`abh3 run CONFIG` on a terminal shows, and commands through, only the supervisor it
starts: a socket another supervisor serves is refused before the TUI opens (exit 2), a
socket that another process serves by the time the TUI attaches is refused too (the
kernel says who serves), and the title names the file and the socket shown."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import os
import pty
import select
import shutil
import struct
import subprocess
import sys
import tempfile
import termios
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from abh3_supervisor.clients.link import Link
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.app import SupervisorApp
from abh3_supervisor.clients.tui.run import not_ours
from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.service.paths import default_socket
from tests.support.rig import TWO_UNITS
from tests.support.terminal import on_a_terminal

ROOT = Path(__file__).resolve().parent.parent
ALTERNATE_SCREEN = b"\x1b[?1049h"  # what a full-screen UI switches to first


def robot(folder: Path) -> Path:
    folder.mkdir()
    config = folder / "robot.yaml"
    shutil.copy(ROOT / "configs" / "demo.yaml", config)
    return config


@contextlib.contextmanager
def serving_headless(config: Path) -> Iterator[subprocess.Popen[str]]:
    run = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", str(config), "--headless"],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert run.stderr is not None
    try:
        for line in run.stderr:
            if "unit right: online" in line:
                break
        yield run
    finally:
        run.terminate()
        run.wait(30)


@pytest.mark.wallclock
def test_another_supervisors_socket_is_refused_before_the_tui_opens(tmp_path: Path) -> None:
    a, b = robot(tmp_path / "a"), robot(tmp_path / "b")
    assert default_socket(str(a)) == default_socket(str(b))  # same name, other folder
    with serving_headless(a) as other:
        code, screen = on_a_terminal(["run", str(b)])
        assert other.poll() is None  # the other one serves on, untouched
    text = screen.decode(errors="replace")
    assert code == 2, text
    assert ALTERNATE_SCREEN not in screen and "starting the supervisor" not in text
    assert "another supervisor serves it already, not the supervisor this `abh3 run`" in text
    assert f"abh3 tui --connect {default_socket(str(b))}" in text


def test_a_socket_served_by_another_process_is_not_attached_to(tmp_path: Path) -> None:
    """What the TUI checks once its child serves: the server's process is that child."""
    path = tmp_path / "s.sock"

    async def check() -> None:
        server = await asyncio.start_unix_server(lambda r, w: None, str(path))
        link = await Link.open(path)
        try:
            not_ours(link, os.getpid())  # served by this very process: ours
            with pytest.raises(Abh3Error, match=f"process {os.getpid()} serves it already"):
                not_ours(link, os.getpid() + 1)
        finally:
            await link.close()
            server.close()

    asyncio.run(check())


def test_the_title_names_the_configuration_and_the_socket() -> None:
    config = parse_config(TWO_UNITS, "robot.yaml")
    shows = "/robots/b/robot.yaml · /run/user/0/abh3/robot.sock"
    app = SupervisorApp(Mirror.of(config, tuple(config.buses)), None, shows=shows)
    assert app.title == f"abh3-supervisor · {shows}"


@pytest.mark.wallclock
def test_the_title_on_screen_names_the_file_and_the_socket() -> None:
    sock = Path(tempfile.mkdtemp(dir="/tmp")) / "s" / "demo.sock"  # short: a title fits
    pid, fd = pty.fork()
    if pid == 0:  # drawn at this size from the first frame (Textual reads COLUMNS first)
        fcntl.ioctl(0, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 200, 0, 0))
        os.environ.update(COLUMNS="200", LINES="40")
        os.chdir(ROOT)
        args = ["run", "configs/demo.yaml", "--socket", str(sock)]
        os.execv(sys.executable, [sys.executable, "-m", "abh3_supervisor", *args])
    title = f"abh3-supervisor · {ROOT / 'configs' / 'demo.yaml'} · {sock}".encode()
    screen = b""
    deadline = time.monotonic() + 60
    try:
        while title not in screen:
            at = screen.find(b"abh3-supervisor")
            assert time.monotonic() < deadline, f"no title: {screen[at : at + 200]!r}"
            ready, _, _ = select.select([fd], [], [], 30)
            assert ready, f"no title: {screen[-800:]!r}"
            screen += os.read(fd, 65536)
    finally:
        os.close(fd)  # the terminal goes away: the TUI stops its supervisor
        os.waitpid(pid, 0)
        shutil.rmtree(sock.parent.parent, ignore_errors=True)
