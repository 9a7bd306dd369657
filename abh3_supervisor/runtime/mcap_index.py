"""The MCAP writer's chunk index, kept on disk beside the recording: the one thing an
``.mcap`` recording would otherwise hold in memory and let grow with its length.

The mcap ``Writer`` keeps one ``ChunkIndex`` record per chunk until ``finish()`` writes
them to the summary; as Python objects they cost about 90 bytes a topic (a dict entry per
channel), and a recording closes a chunk every ``FLUSH_S`` (0.5 s) so that a kill loses
little: an hour of four units (43 topics) would hold 28 MB. Here each record is written,
as the bytes ``finish()`` would write, to an unlinked file in the recording's directory
(about 4 MB an hour of four units; nothing is left behind, even after a ``kill -9``), and
read back once, by ``finish()``. This reaches into the writer's private list; with an
mcap whose writer has none it does nothing.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

_PRIVATE = "_Writer__chunk_indices"  # mcap.writer.Writer's list, by its mangled name
BLOCK = 1 << 20  # read back in blocks at the end


class _Spilled:
    """All the records at once, as ``finish()`` asks each index to write itself."""

    def __init__(self, file: IO[bytes]) -> None:
        self.file = file

    def write(self, builder: Any) -> None:
        self.file.seek(0)
        while block := self.file.read(BLOCK):
            builder.write(block)


class SpilledChunkIndexes:
    """Stands in for the writer's list: ``append()`` writes a record's bytes to the file;
    iterating gives one object that writes them all, in order."""

    def __init__(self, directory: Path) -> None:
        self.file = tempfile.TemporaryFile(dir=directory, prefix=".mcap-index-")  # noqa: SIM115
        self.count = 0
        self.size = 0  # bytes on disk, none in memory

    def append(self, index: Any) -> None:
        from mcap.data_stream import RecordBuilder

        builder: Any = RecordBuilder()
        index.write(builder)
        data = builder.end()
        self.file.write(data)  # buffered; an OSError is the disk's: the recording's failure
        self.size += len(data)
        self.count += 1

    def __iter__(self) -> Iterator[_Spilled]:
        if self.count:
            self.file.flush()
            yield _Spilled(self.file)

    def close(self) -> None:
        self.file.close()


def spill_chunk_indexes(mcap_writer: Any, directory: Path) -> SpilledChunkIndexes | None:
    """Install the spilled index in a new mcap ``Writer`` (before its first chunk)."""
    if getattr(mcap_writer, _PRIVATE, None) != []:
        return None  # another mcap, or chunks already written: leave it as it is
    spilled = SpilledChunkIndexes(directory)
    setattr(mcap_writer, _PRIVATE, spilled)
    return spilled
