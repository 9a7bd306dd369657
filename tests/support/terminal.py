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

ROOT = Path(__file__).resolve().parent.parent.parent


def in_a_terminal(args: list[str]) -> tuple[int, int]:
    """``abh3 ARGS`` on a pseudo-terminal, once its screen shows both units online."""
    pid, fd = pty.fork()
    if pid == 0:
        os.chdir(ROOT)
        os.execv(sys.executable, [sys.executable, "-m", "abh3_supervisor", *args])
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 180, 0, 0))
    screen = b""
    while screen.count(b"online") < 2:
        ready, _, _ = select.select([fd], [], [], 30)
        assert ready, f"no TUI output: {screen[-500:]!r}"
        screen += os.read(fd, 65536)
    return pid, fd
