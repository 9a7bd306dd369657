"""A bus that never hands us our own frames back.

On python-can's ``udp_multicast`` every member of the group receives each datagram, its
sender too, and nothing turns that off. Our machines must not see their own frames: the
supervisor would take its own DP0 commands for another host's, a recording would hold
each sent frame twice. :class:`EchoFilter` remembers what it sent and drops the first
received copy of each. A frame another host sent that equals one of ours is dropped in
its place, once; the copy of ours that then arrives has nothing left to match and goes
through — so a second host sending exactly our frames is still seen, one frame late.
Entries whose copy never came (a full socket buffer) are forgotten after ``EXPIRY_S``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can

EXPIRY_S = 1.0
MAX_PENDING = 4096  # sent frames awaiting their copy: a bound, whatever happens


class EchoFilter(can.BusABC):
    def __init__(self, bus: can.BusABC, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.inner = bus
        self._clock = clock
        self._pending: deque[tuple[float, int, bytes]] = deque(maxlen=MAX_PENDING)
        self._lock = threading.Lock()  # a reader thread receives while the loop sends
        self.echoes_dropped = 0
        super().__init__(channel=bus.channel_info)
        self.channel_info = bus.channel_info
        self._can_protocol = bus.protocol

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        entry = (self._clock(), msg.arbitration_id, bytes(msg.data))
        with self._lock:  # before sending: the copy may come back before send returns
            self._pending.append(entry)
        try:
            self.inner.send(msg, timeout)
        except BaseException:
            with self._lock:
                self._forget(entry)
            raise

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        if msg is None or self._is_echo(msg):
            return None, False  # recv() goes on waiting for the rest of its timeout
        return msg, True  # the inner bus applied its filters

    def _is_echo(self, msg: can.Message) -> bool:
        data, now = bytes(msg.data), self._clock()
        with self._lock:
            pending = self._pending
            while pending and pending[0][0] < now - EXPIRY_S:
                pending.popleft()
            for entry in pending:
                if entry[1] == msg.arbitration_id and entry[2] == data:
                    self._forget(entry)
                    self.echoes_dropped += 1
                    return True
        return False

    def _forget(self, entry: tuple[float, int, bytes]) -> None:
        with contextlib.suppress(ValueError):
            self._pending.remove(entry)

    def fileno(self) -> int:
        return self.inner.fileno()

    @property
    def state(self) -> can.BusState:
        return self.inner.state

    @state.setter
    def state(self, new: can.BusState) -> None:
        self.inner.state = new

    def set_filters(self, filters: Any = None) -> None:
        self.inner.set_filters(filters)

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()
