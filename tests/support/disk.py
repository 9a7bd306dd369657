"""A file that fills up: the disk-full paths of recordings."""

from __future__ import annotations

import errno
from typing import Any


class FillsUp:
    """A raw file that takes ``room`` more bytes, then reports the disk full (as write(2)
    does: a short write first, then ENOSPC)."""

    def __init__(self, real: Any, room: int) -> None:
        self.real, self.room = real, room

    def write(self, data: bytes) -> int:
        if self.room <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        part = bytes(data[: self.room])
        self.room -= len(part)
        return int(self.real.write(part))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)
