"""At most one log line per key and interval: a flood of bad frames must not flood the log."""

from __future__ import annotations

from collections.abc import Hashable


class Throttle:
    def __init__(self, interval: float = 1.0) -> None:
        self.interval = interval
        self._last: dict[Hashable, float] = {}
        self._held: dict[Hashable, int] = {}

    def allow(self, key: Hashable, now: float) -> int | None:
        """None to hold this line back; else how many lines of ``key`` were held back."""
        last = self._last.get(key)
        if last is not None and now - last < self.interval:
            self._held[key] = self._held.get(key, 0) + 1
            return None
        self._last[key] = now
        return self._held.pop(key, 0)


def held_note(held: int) -> str:
    return f" ({held} more like it since the last line not shown)" if held else ""
