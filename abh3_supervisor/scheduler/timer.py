"""A one-shot deadline timer on the event loop, precise to well under a millisecond.

asyncio's ``call_at`` wakes through ``epoll_wait``, whose timeout has millisecond
granularity (rounded up), so a periodic command would leave up to 1 ms late. On Linux a
``timerfd`` armed at the absolute CLOCK_MONOTONIC deadline (the clock ``loop.time()``
reads) wakes the loop through ``add_reader`` at the right moment instead. Elsewhere, or
if the timerfd cannot be made, it falls back to ``call_at``.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import os
import sys
import time
from collections.abc import Callable

_CLOCK_MONOTONIC = 1
_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        libc.timerfd_create  # noqa: B018 - probe that the symbol exists
    except (OSError, AttributeError):
        return None
    return libc


_LIBC = _libc()


class DeadlineTimer:
    def __init__(self, loop: asyncio.AbstractEventLoop, callback: Callable[[], None]) -> None:
        self.loop, self.callback = loop, callback
        self.when: float | None = None
        self._handle: asyncio.TimerHandle | None = None
        self._fd = -1
        self._spec = _Itimerspec()  # reused: arming happens on every scheduler step
        # the loop must tell time with CLOCK_MONOTONIC for absolute timerfd deadlines
        if _LIBC is not None and abs(loop.time() - time.monotonic()) < 0.01:
            fd = _LIBC.timerfd_create(_CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
            if fd >= 0:
                self._fd = fd
                loop.add_reader(fd, self._on_readable)

    @property
    def precise(self) -> bool:
        return self._fd >= 0

    def arm(self, when: float) -> None:
        """Fire at ``when`` — or earlier: a later deadline keeps the armed one (lazy re-arm).

        The callback then finds nothing due and arms again; that costs one spurious wake-up
        now and then instead of a system call on every scheduler step.
        """
        if self.when is not None and self.when <= when:
            return
        self.when = when
        if self._fd >= 0:
            when = max(when, 1e-6)  # an all-zero it_value would disarm instead
            seconds = int(when)
            value = self._spec.it_value
            value.tv_sec, value.tv_nsec = seconds, int((when - seconds) * 1e9)
            assert _LIBC is not None
            _LIBC.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, ctypes.byref(self._spec), None)
        else:
            if self._handle is not None:
                self._handle.cancel()
            self._handle = self.loop.call_at(when, self._fire)

    def cancel(self) -> None:
        self.when = None
        if self._fd >= 0:
            assert _LIBC is not None
            value = self._spec.it_value
            value.tv_sec, value.tv_nsec = 0, 0  # all zero: disarm
            _LIBC.timerfd_settime(self._fd, 0, ctypes.byref(self._spec), None)
        elif self._handle is not None:
            self._handle.cancel()
            self._handle = None

    def close(self) -> None:
        self.cancel()
        if self._fd >= 0:
            self.loop.remove_reader(self._fd)
            os.close(self._fd)
            self._fd = -1
        self._spec = _Itimerspec()  # reused: arming happens on every scheduler step

    def _on_readable(self) -> None:
        try:
            os.read(self._fd, 8)
        except BlockingIOError:
            return  # re-armed after expiring: nothing due now
        self._fire()

    def _fire(self) -> None:
        self.when = None
        self._handle = None
        self.callback()
