"""A bus that never hands us our own frames back.

On python-can's ``udp_multicast`` every member of the group receives each datagram, its
sender too: :class:`~abh3_supervisor.simulator.multicast.MulticastBus` (the simulator's
transport) has the kernel drop our copies. Any other bus that hears itself
(``receive_own_messages``) is an :class:`EchoFilter`: it remembers what it sent and drops
the first received copy of each by identifier and data. A frame another host sent that
equals one of ours is dropped in its place, once; the copy of ours that then arrives has
nothing left to match and goes through — so a second host sending exactly our frames is
still seen, one frame late. Entries whose copy never came are forgotten after
``EXPIRY_S``.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can

from abh3_supervisor.simulator.multicast import EXPIRY_S, MulticastBus

MAX_PENDING = 4096  # sent frames awaiting their copy: a bound, whatever happens
__all__ = ["EXPIRY_S", "EchoFilter", "without_own_frames"]


class EchoFilter(can.BusABC):
    """``bus``, as this one, without the copies of what this one sent."""

    def __init__(self, bus: can.BusABC, *, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(channel=bus.channel_info)  # before inner: its filters stay its own
        self.inner, self.clock, self.channel_info = bus, clock, bus.channel_info
        self.lock = threading.Lock()  # a reader thread may receive while the loop sends
        self.pending: deque[tuple[float, int, bytes]] = deque(maxlen=MAX_PENDING)
        self.echoes_dropped = 0

    @property
    def protocol(self) -> can.CanProtocol:
        return self.inner.protocol

    @property
    def state(self) -> can.BusState:
        return self.inner.state

    @state.setter
    def state(self, new: can.BusState) -> None:
        self.inner.state = new

    def fileno(self) -> int:
        return self.inner.fileno()

    def set_filters(self, filters: Any = None) -> None:
        if hasattr(self, "inner"):  # BusABC's constructor sets none
            self.inner.set_filters(filters)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        entry = (self.clock(), msg.arbitration_id, bytes(msg.data))
        with self.lock:  # before sending: the copy may come back before send returns
            self.pending.append(entry)
        try:
            self.inner.send(msg, timeout)
        except BaseException:
            with self.lock, contextlib.suppress(ValueError):
                self.pending.remove(entry)
            raise

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        while msg is not None and self.is_echo(msg):
            msg = self.inner.recv(0)  # what waits behind it: a copy never ends a read
        return msg, True  # the inner bus applied its filters

    def is_echo(self, msg: can.Message) -> bool:
        data, now = bytes(msg.data), self.clock()
        with self.lock:
            pending = self.pending
            while pending and pending[0][0] < now - EXPIRY_S:
                pending.popleft()
            for entry in pending:
                if entry[1] == msg.arbitration_id and entry[2] == data:
                    pending.remove(entry)
                    self.echoes_dropped += 1
                    return True
        return False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


def without_own_frames(bus: can.BusABC, interface: str, channel: str) -> can.BusABC:
    """``bus`` (which hears its own frames), opened as ``interface`` on ``channel``,
    wrapped so that it does not."""
    if interface == "udp_multicast":
        return MulticastBus(bus, channel)
    return EchoFilter(bus)
