"""A few log lines per key and interval at most: a flood of bad frames must not flood the
log, while an ordinary set-then-clear still shows both lines."""

from __future__ import annotations

from collections import deque
from collections.abc import Hashable


class Throttle:
    def __init__(self, interval: float = 1.0, burst: int = 1) -> None:
        self.interval, self.burst = interval, burst
        self._shown: dict[Hashable, deque[float]] = {}
        self._held: dict[Hashable, int] = {}

    def allow(self, key: Hashable, now: float) -> int | None:
        """None to hold this line back; else how many lines of ``key`` were held back."""
        shown = self._shown.setdefault(key, deque(maxlen=self.burst))
        if len(shown) == self.burst and now - shown[0] < self.interval:
            self._held[key] = self._held.get(key, 0) + 1
            return None
        shown.append(now)
        return self._held.pop(key, 0)


def held_note(held: int) -> str:
    return f" ({held} more like it since the last line not shown)" if held else ""
