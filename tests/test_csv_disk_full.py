"""A full disk under the CSV plugin: whole rows only, and an error naming the file."""

from __future__ import annotations

import csv
import errno
from pathlib import Path
from typing import Any

import pytest

from abh3_plugins.csv_output import COLUMNS, _File


class FillsUp:
    """A raw file that takes ``room`` more bytes, then reports the disk full (as write(2)
    does: a short write first, then ENOSPC)."""

    def __init__(self, real: Any, room: int) -> None:
        self.real, self.room = real, room

    def write(self, data: bytes) -> int:
        if self.room <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        part = data[: self.room]
        self.room -= len(part)
        return int(self.real.write(part))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)


def row(i: int) -> dict[str, Any]:
    return {c: i for c in COLUMNS}


def test_a_full_disk_leaves_whole_rows_and_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    f = _File(path, 0, 0)
    for i in range(10):
        f.write(row(i))
    f.flush()
    f.handle = FillsUp(f.handle, room=150)  # type: ignore[assignment]
    for i in range(10, 20):
        f.write(row(i))
    with pytest.raises(OSError, match=r"No space left on device: '.*out\.csv'"):
        f.flush()
    text = path.read_text(encoding="utf-8")
    assert text.endswith("\n")  # cut back to the last whole row
    rows = list(csv.DictReader(text.splitlines()))
    assert [r["unit"] for r in rows] == [str(i) for i in range(10)]
