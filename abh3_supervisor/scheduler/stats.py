"""Per-unit exchange statistics, cheap to update on the bus path, computed on demand."""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field

RTT_WINDOW = 1024  # round trips the RTT percentiles are taken over


def _rank(n: int, q: float) -> int:
    """The index of the nearest-rank ``q`` percentile (0–100) among ``n`` sorted samples."""
    return max(0, min(n - 1, round(q / 100 * n + 0.5) - 1))


def percentile(samples: list[float], q: float) -> float | None:
    """Nearest-rank percentile (``q`` in 0–100); ``None`` without samples."""
    return sorted(samples)[_rank(len(samples), q)] if samples else None


@dataclass
class UnitStats:
    requested_rate_hz: float
    commands_sent: int = 0
    replies: int = 0
    unsolicited: int = 0
    timeouts: int = 0
    send_errors: int = 0
    polls_sent: int = 0
    broadcasts: int = 0
    malformed: int = 0  # frames with our ids but the wrong length or kind: never counted
    gaps: int = 0  # times no exchange completed within the drive's timeout
    last_seen: float | None = None
    # the last RTT_WINDOW round trips, in arrival order and kept sorted: a percentile is
    # then an index, not a sort of the window on every snapshot and diagnostics message
    _rtts: deque[float] = field(default_factory=deque)
    _rtts_sorted: list[float] = field(default_factory=list)
    _reply_times: deque[float] = field(default_factory=lambda: deque(maxlen=256))

    def on_reply(self, now: float, rtt: float | None) -> None:
        self.replies += 1
        self.last_seen = now
        self._reply_times.append(now)
        if rtt is not None:
            if len(self._rtts) >= RTT_WINDOW:
                del self._rtts_sorted[bisect.bisect_left(self._rtts_sorted, self._rtts.popleft())]
            self._rtts.append(rtt)
            bisect.insort(self._rtts_sorted, rtt)

    def achieved_rate_hz(self, now: float, window: float = 2.0) -> float:
        """Solicited replies per second over the last ``window`` seconds."""
        # list(deque) copies in one C call, atomic under the GIL: the TUI reads these from
        # its own thread while the bus thread appends
        times = list(self._reply_times)  # in arrival order: the window is a tail of it
        recent = times[bisect.bisect_left(times, True, key=lambda t: now - t <= window) :]
        if len(recent) < 2:
            return 0.0
        # measure between replies while they flow (no bias from where `now` falls between
        # two of them); once they stop, stretch to `now` so the rate decays
        last = recent[-1] if now - recent[-1] <= window / 4 else now
        span = last - recent[0]
        return (len(recent) - 1) / span if span > 0 else 0.0

    def rtt_ms(self, q: float) -> float | None:
        return self.rtts_ms(q)[0]

    def rtts_ms(self, *qs: float) -> tuple[float | None, ...]:
        """The ``qs`` percentiles [ms] of one window, from any thread: a copy of the sorted
        window (one C-level copy, whole under the GIL and in a free-threaded build alike) is
        indexed, never the list the loop changes between a read of its length and an index
        into it. Taken between the loop's drop of the oldest sample and its sort of the new
        one, the window is one sample short; every percentile of one call is of one window."""
        ordered = list(self._rtts_sorted)
        return tuple(None if not ordered else ordered[_rank(len(ordered), q)] * 1000 for q in qs)
