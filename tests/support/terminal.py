"""``abh3`` on a pseudo-terminal."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import sys
import termios
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parent.parent.parent


def spawn(args: list[str]) -> tuple[int, int]:
    """``abh3 ARGS`` on a new pseudo-terminal: its pid and the terminal's fd."""
    pid, fd = pty.fork()
    if pid == 0:
        os.chdir(ROOT)
        os.execv(sys.executable, [sys.executable, "-m", "abh3_supervisor", *args])
    return pid, fd


def in_a_terminal(args: list[str]) -> tuple[int, int]:
    """``abh3 ARGS`` on a pseudo-terminal, once its screen shows both units online."""
    pid, fd = spawn(args)
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 180, 0, 0))
    screen = b""
    while screen.count(b"online") < 2:
        ready, _, _ = select.select([fd], [], [], 30)
        assert ready, f"no TUI output: {screen[-500:]!r}"
        screen += os.read(fd, 65536)
    return pid, fd


class Ended(NamedTuple):
    code: int  # the exit code
    screen: bytes  # what it wrote to the terminal from then on


def ended(pid: int, fd: int) -> Ended:
    """Read the terminal until the program has gone (bounded); the terminal is closed."""
    screen = b""
    while True:
        ready, _, _ = select.select([fd], [], [], 60)
        assert ready, f"no end: {screen[-500:]!r}"
        try:
            data = os.read(fd, 65536)
        except OSError:  # EIO: the child's side closed
            break
        if not data:
            break
        screen += data
    _, status = os.waitpid(pid, 0)
    os.close(fd)
    return Ended(os.waitstatus_to_exitcode(status), screen)


def on_a_terminal(args: list[str]) -> Ended:
    """``abh3 ARGS`` on a pseudo-terminal until it ends: its exit code and its screen."""
    return ended(*spawn(args))
