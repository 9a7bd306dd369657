"""What waits for the network, bounded: the hooks put, the link's sender takes.

Two lanes: ``keep`` (status, events: each one says something once) before ``lossy``
(unit states and health: the next one says it again); and ``last``, one message sent
once both are empty (the orderly ``offline``: after the last states). Beyond ``size``
messages the oldest lossy one goes first, then the oldest kept one; each is counted, and
the first drop is said once in the log. ``put`` never blocks on the network: a lock held
for a deque operation is all a hook waits for.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass

log = logging.getLogger("abh3_plugins.mqtt")


@dataclass(frozen=True, slots=True)
class Message:
    topic: str
    payload: bytes
    qos: int
    retain: bool


class Outbox:
    def __init__(self, size: int, name: str) -> None:
        self.size, self.name = size, name
        self.dropped = 0
        self._keep: deque[Message] = deque()
        self._lossy: deque[Message] = deque()
        self._last: Message | None = None
        self._ready = threading.Condition()
        self._closed = False

    def __len__(self) -> int:
        return len(self._keep) + len(self._lossy) + (self._last is not None)

    def put(self, message: Message, *, lossy: bool) -> None:
        with self._ready:
            (self._lossy if lossy else self._keep).append(message)
            while len(self) > self.size:
                (self._lossy or self._keep).popleft()
                self.dropped += 1
                if self.dropped == 1:
                    log.warning(
                        "mqtt %s: the broker does not keep up: more than %d messages waiting, "
                        "the oldest states are dropped (counted in health.mqtt.dropped)",
                        self.name,
                        self.size,
                    )
            self._ready.notify()

    def put_last(self, message: Message) -> None:
        """``message`` after everything queued, and after whatever is put meanwhile."""
        with self._ready:
            self._last = message
            self._ready.notify()

    def take(self, timeout: float | None) -> Message | None:
        """The next message (kept ones first), or None after ``timeout`` or once closed."""
        with self._ready:
            if not self._closed and not len(self):
                self._ready.wait(timeout)
            if self._keep:
                return self._keep.popleft()
            if self._lossy:
                return self._lossy.popleft()
            last, self._last = self._last, None
            return last

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify_all()
