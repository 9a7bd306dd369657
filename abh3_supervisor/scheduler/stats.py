"""Per-unit exchange statistics, cheap to update on the bus path, computed on demand."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field


def percentile(samples: list[float], q: float) -> float | None:
    """Nearest-rank percentile (``q`` in 0–100); ``None`` without samples."""
    if not samples:
        return None
    ordered = sorted(samples)
    rank = max(0, min(len(ordered) - 1, round(q / 100 * len(ordered) + 0.5) - 1))
    return ordered[rank]


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
    _rtts: deque[float] = field(default_factory=lambda: deque(maxlen=1024))
    _reply_times: deque[float] = field(default_factory=lambda: deque(maxlen=256))

    def on_reply(self, now: float, rtt: float | None) -> None:
        self.replies += 1
        self.last_seen = now
        self._reply_times.append(now)
        if rtt is not None:
            self._rtts.append(rtt)

    def achieved_rate_hz(self, now: float, window: float = 2.0) -> float:
        """Solicited replies per second over the last ``window`` seconds."""
        # list(deque) copies in one C call, atomic under the GIL: the TUI reads these from
        # its own thread while the bus thread appends
        recent = [t for t in list(self._reply_times) if now - t <= window]
        if len(recent) < 2:
            return 0.0
        # measure between replies while they flow (no bias from where `now` falls between
        # two of them); once they stop, stretch to `now` so the rate decays
        last = recent[-1] if now - recent[-1] <= window / 4 else now
        span = last - recent[0]
        return (len(recent) - 1) / span if span > 0 else 0.0

    def rtt_ms(self, q: float) -> float | None:
        value = percentile(list(self._rtts), q)
        return None if value is None else value * 1000
