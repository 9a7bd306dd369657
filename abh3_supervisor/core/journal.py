"""What the bus loop writes once, for every watcher to read at its own pace.

The supervisor writes each of its events here, numbered, once (:meth:`Journal.write`, on
the loop; a DP0 reply's entry carries the unit's feedback, setpoint and inputs as they
stood after it, so no reader looks at live state). Watchers — the plugins' workers, the
headless log — each hold a :class:`Reader` and take what is new when they wake, from
any thread: nothing is handed to each watcher per reply. The ring is bounded; what a
slow reader finds overwritten is counted in :attr:`Reader.missed`, never waited for.

Lock-free: the loop fills a slot before it publishes the slot's number, and a reader
checks each slot's number, so a slot overwritten while it reads is a miss, not a wrong
event.
"""

from __future__ import annotations

from typing import Any

SIZE = 1 << 13  # entries: about 10 s of 4 units at 100 Hz with their status packets

# (number, event, sample): sample is (feedback, setpoint, inputs) after a DP0 reply, else None
Entry = tuple[int, Any, Any]


class Journal:
    def __init__(self, size: int = SIZE) -> None:
        if size & (size - 1):
            raise ValueError("the journal's size is a power of two")
        self.mask = size - 1
        self.ring: list[Entry | None] = [None] * size
        self.seq = 0  # the last number written

    def write(self, event: object, sample: object = None) -> None:
        """On the loop only."""
        seq = self.seq + 1
        self.ring[seq & self.mask] = (seq, event, sample)
        self.seq = seq  # published after the slot is filled

    def reader(self) -> Reader:
        """A reader of what is written from now on."""
        return Reader(self, self.seq)


class Reader:
    """One watcher's place in the journal (used by one thread at a time)."""

    def __init__(self, journal: Journal, cursor: int) -> None:
        self.journal = journal
        self.cursor = cursor  # the last number read
        self.missed = 0  # entries overwritten before this reader came to them

    def read(self) -> list[Entry]:
        """Every entry written since the last read, oldest first."""
        journal = self.journal
        last = journal.seq
        first = self.cursor + 1
        oldest = last - journal.mask  # the ring holds mask + 1 entries
        if first < oldest:
            self.missed += oldest - first
            first = oldest
        ring, mask = journal.ring, journal.mask
        out: list[Entry] = []
        for seq in range(first, last + 1):
            entry = ring[seq & mask]
            if entry is None or entry[0] != seq:  # overwritten while we read
                self.missed += 1
            else:
                out.append(entry)
        self.cursor = last
        return out
