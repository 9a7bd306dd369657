"""The MCAP writer's chunk index, packed: what an ``.mcap`` recording holds in memory and
lets grow with its length.

The mcap ``Writer`` keeps one ``ChunkIndex`` record per chunk until ``finish()`` writes
them to the summary; as Python objects they cost about 90 bytes a topic (a dict entry per
channel), and a recording closes a chunk every ``FLUSH_S`` (0.5 s) so that a kill loses
little. Kept as the bytes ``finish()`` writes (10 bytes a topic, ~70 a chunk) instead, an
hour of four units (43 topics) costs about 4 MB rather than 28. This reaches into the
writer's private list; with an mcap whose writer has none it does nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

_PRIVATE = "_Writer__chunk_indices"  # mcap.writer.Writer's list, by its mangled name


class _Bytes:
    """All the records at once, as ``finish()`` asks each index to write itself."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def write(self, builder: Any) -> None:
        builder.write(self.data)


class PackedChunkIndexes:
    """Stands in for the writer's list: ``append()`` keeps a record's bytes; iterating
    gives one object that writes them all, in order."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.count = 0

    def append(self, index: Any) -> None:
        from mcap.data_stream import RecordBuilder

        builder: Any = RecordBuilder()
        index.write(builder)
        self.data += builder.end()
        self.count += 1

    def __iter__(self) -> Iterator[_Bytes]:
        if self.data:
            yield _Bytes(bytes(self.data))


def pack_chunk_indexes(mcap_writer: Any) -> PackedChunkIndexes | None:
    """Install the packed index in a new mcap ``Writer`` (before its first chunk)."""
    if getattr(mcap_writer, _PRIVATE, None) != []:
        return None  # another mcap, or chunks already written: leave it as it is
    packed = PackedChunkIndexes()
    setattr(mcap_writer, _PRIVATE, packed)
    return packed
