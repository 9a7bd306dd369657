"""Messages into the mcap ``Writer``'s chunk at the cost of one ``struct.pack``: what its
``add_message`` does — the record, the chunk's message index, the file's statistics —
without building a ``Message`` object and packing its fields one by one (3.5 µs a
message, most of what an ``.mcap`` recording still cost the loop once our messages were
encoded by :mod:`.cdr`). The chunk's message indexes are written at its end in one pack
too. The file is byte for byte the one ``add_message`` writes (tests/test_mcap_cdr.py).

Like :mod:`.mcap_index`, this reaches into the writer's private state (by its mangled
names); with an mcap whose writer has none of it, :func:`fast_add` gives ``add_message``
itself.
"""

from __future__ import annotations

import itertools
import struct
from collections.abc import Callable
from typing import Any

from mcap.opcode import Opcode
from mcap.records import MessageIndex

# opcode, record length, channel id, sequence, log time, publish time; then the data
_MESSAGE = struct.Struct("<BQHIQQ")
_FIXED = 22  # the record's length without its data
_PRIVATE = (
    "_Writer__statistics",
    "_Writer__chunk_builder",
    "_Writer__chunk_size",
    "_Writer__finalize_chunk",
)

AddMessage = Callable[[int, int, bytes, int], None]  # channel, log time, data, sequence


class _Index(MessageIndex):
    """A chunk's message index for one channel, written in one pack."""

    def write(self, stream: Any) -> None:
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write2(self.channel_id)
        stream.write4(len(self.records) * 16)
        stream.write(struct.pack(f"<{2 * len(self.records)}Q", *itertools.chain(*self.records)))
        stream.finish_record()


class _Messages:
    def __init__(self, writer: Any) -> None:
        self.stats = writer._Writer__statistics
        self.chunk = writer._Writer__chunk_builder
        self.chunk_size: int = writer._Writer__chunk_size
        self.finish_chunk: Callable[[], None] = writer._Writer__finalize_chunk

    def add(self, channel: int, log_time: int, data: bytes, sequence: int) -> None:
        """``add_message(channel, log_time, data, publish_time=log_time, sequence)``."""
        stats, chunk = self.stats, self.chunk
        if stats.message_count == 0 or log_time < stats.message_start_time:
            stats.message_start_time = log_time
        if log_time > stats.message_end_time:
            stats.message_end_time = log_time
        stats.channel_message_counts[channel] += 1
        stats.message_count += 1
        if chunk.num_messages == 0 or log_time < chunk.message_start_time:
            chunk.message_start_time = log_time
        if log_time > chunk.message_end_time:
            chunk.message_end_time = log_time
        buffer = chunk.record_writer._buffer  # replaced at each chunk's end: looked up
        index = chunk.message_indices.get(channel)
        if index is None:
            index = chunk.message_indices[channel] = _Index(channel, [])
        index.records.append((log_time, buffer.tell()))
        chunk.num_messages += 1
        buffer.write(_MESSAGE.pack(Opcode.MESSAGE, _FIXED + len(data), channel, sequence,
                                   log_time, log_time))  # fmt: skip
        buffer.write(data)
        if buffer.tell() > self.chunk_size:
            self.finish_chunk()


def fast_add(writer: Any) -> AddMessage:
    """``writer``'s messages added in one pack, or by ``add_message`` if it is another
    mcap (before its first message)."""
    chunk = getattr(writer, "_Writer__chunk_builder", None)
    ready = all(hasattr(writer, name) for name in _PRIVATE)
    if (
        not ready
        or chunk is None
        or chunk.num_messages
        or not hasattr(chunk.record_writer, "_buffer")
    ):
        return lambda channel, ns, data, sequence: writer.add_message(
            channel, ns, data, ns, sequence
        )
    return _Messages(writer).add
