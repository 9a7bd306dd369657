"""The in-process simulator's bus: python-can's ``virtual`` bus, and a doorbell for the drives.

``abh3 run`` with ``simulate:`` runs the drives' pump and the supervisor's on one event
loop, on two virtual buses of one channel. python-can reads a virtual bus by waiting in
``recv`` (a thread): the supervisor's bus is read so, and any host on the channel (a
test's second host too) wakes its loop at once. The drives' bus is a :class:`LocalBus`
with a doorbell: its file descriptor (an eventfd) is rung when a :class:`LocalBus` of
this process sends on the channel, and its pump watches it as it watches SocketCAN — so
the loop steps the drives right after the step that commanded them, without a thread
or a second wake-up (4 units at 100 Hz wake the loop once a period). The first read
after a ring silences it; frames that come later ring again. A frame from any other
sender on the channel rings nothing: the drives read it at their next step, at the
latest when the supervisor next sends.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

_RING = (1).to_bytes(8, sys.byteorder)  # an eventfd adds this; a pipe just holds it
_BELLS: dict[str, list[LocalBus]] = {}  # channel → the doorbells on it in this process


def _bell() -> tuple[int, int]:
    """(read end, write end) of a doorbell: an eventfd where there is one, else a pipe."""
    if hasattr(os, "eventfd"):
        fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        return fd, fd
    read, write = os.pipe()
    os.set_blocking(read, False)
    os.set_blocking(write, False)
    return read, write


class LocalBus(VirtualBus):
    """python-can's virtual bus on ``channel``; ``doorbell``: with a file descriptor that
    the other :class:`LocalBus` of this process ring when they send (else none: read
    by a thread, as python-can's)."""

    def __init__(self, channel: str, *, doorbell: bool = False, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self.local_channel = channel
        self.bell = self.ringer = -1
        self.rung = False
        if doorbell:
            self.bell, self.ringer = _bell()
            _BELLS.setdefault(channel, []).append(self)

    def fileno(self) -> int:
        return self.bell if self.bell >= 0 else super().fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        super().send(msg, timeout)
        for bus in _BELLS.get(self.local_channel, ()):
            if not bus.rung and bus is not self:
                bus.rung = True
                with contextlib.suppress(OSError):  # a pipe full of rings: rung already
                    os.write(bus.ringer, _RING)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self.rung:  # before the read: a frame sent after it rings again
            self.rung = False
            with contextlib.suppress(OSError):
                os.read(self.bell, 4096)
        return super().recv(timeout)

    def shutdown(self) -> None:
        bells = _BELLS.get(self.local_channel, [])
        if self in bells:
            bells.remove(self)
            if not bells:
                del _BELLS[self.local_channel]
            os.close(self.bell)
            if self.ringer != self.bell:
                os.close(self.ringer)
        super().shutdown()
