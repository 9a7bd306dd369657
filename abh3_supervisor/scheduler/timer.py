"""A one-shot deadline timer on the event loop, precise to well under a millisecond.

asyncio's ``call_at`` wakes through ``epoll_wait``, whose timeout has millisecond
granularity (rounded up), so a periodic command would leave up to 1 ms late. On Linux a
``timerfd`` armed at the absolute CLOCK_MONOTONIC deadline (the clock ``loop.time()``
reads) wakes the loop through ``add_reader`` at the right moment instead. Elsewhere, or
if the timerfd cannot be made, it falls back to ``call_at``.

``repeating``: a schedule of periodic deadlines (the pump's) re-arms the timer at every
firing, a system call each time. Armed from its own callback, the timer therefore guesses
that the next deadline will be as far after this one as this one was after the last
firing, and lets the kernel repeat it (the timerfd's interval, a little short, so that a
repetition never comes after its deadline): a deadline that falls just after the
repetition then costs nothing; any other is armed as before.

``late_s``: the most a firing came after its deadline since :meth:`take_late` (a loop
that runs late, for want of CPU: what slows the live view, service/view_pace.py).
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
# a repetition is this much shorter than the interval it repeats: the deadlines, floats,
# land within ±1 ns of their grid, and a repetition must never come after one
_DRIFT_NS = 2
# a deadline this little after the next repetition keeps it (the repetitions drift this
# far ahead of the grid before they are set again: once every 1000 periods)
_SLACK_NS = 2000
_MIN_INTERVAL_NS = 100_000  # nothing this close together repeats: no such schedule


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
    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        callback: Callable[[], None],
        *,
        repeating: bool = False,
    ) -> None:
        self.loop, self.callback = loop, callback
        self.when: float | None = None
        self._handle: asyncio.TimerHandle | None = None
        self._fd = -1
        self._repeating = repeating
        self._next_ns = -1  # the timerfd's next expiry; -1: not armed
        self._interval_ns = 0  # the kernel repeats it so (0: once)
        self._fired_ns = -1  # the expiry whose callback runs now; -1: outside the callback
        self._armed = False  # the callback armed or cancelled the timer
        self._spec = _Itimerspec()  # reused: arming happens on every scheduler step
        self.late_s = 0.0
        # the loop must tell time with CLOCK_MONOTONIC for absolute timerfd deadlines
        if _LIBC is not None and abs(loop.time() - time.monotonic()) < 0.01:
            fd = _LIBC.timerfd_create(_CLOCK_MONOTONIC, os.O_NONBLOCK | os.O_CLOEXEC)
            if fd >= 0:
                self._fd = fd
                loop.add_reader(fd, self._on_readable)

    @property
    def precise(self) -> bool:
        return self._fd >= 0

    def take_late(self) -> float:
        """The most a firing came after its deadline since the last call (0: none late)."""
        late, self.late_s = self.late_s, 0.0
        return late

    def arm(self, when: float) -> None:
        """Fire at ``when`` — or earlier: a later deadline keeps the armed one (lazy re-arm).

        The callback then finds nothing due and arms again; that costs one spurious wake-up
        now and then instead of a system call on every scheduler step. From the callback, a
        repetition (``repeating``) is kept only for a deadline at most ``_SLACK_NS`` after
        it (else the period is guessed again); outside it, as any earlier expiry — a frame
        that moves the deadline later (the simulator's drives, at every command) then costs
        no system call, and the early firing's callback sets the timer right.
        """
        if self._fd >= 0:
            self._arm_fd(when)
            return
        if self.when is not None and self.when <= when:
            return
        self.when = when
        if self._handle is not None:
            self._handle.cancel()
        self._handle = self.loop.call_at(when, self._fire_late)

    def _arm_fd(self, when: float) -> None:
        self._armed = True
        when = max(when, 1e-6)  # an all-zero it_value would disarm instead
        seconds = int(when)
        nanoseconds = int((when - seconds) * 1e9)
        at = seconds * 1_000_000_000 + nanoseconds
        armed = self._next_ns
        # it fires in time: lazily kept (outside the callback a repetition too: fired early,
        # its callback arms again), or the repetition meant for this deadline
        kept = not self._interval_ns or at - armed <= _SLACK_NS or self._fired_ns < 0
        if 0 <= armed <= at and kept:
            return
        interval = 0
        if self._repeating and self._fired_ns >= 0:  # from the callback: guess the period
            gap = at - self._fired_ns
            interval = gap - _DRIFT_NS if gap >= _MIN_INTERVAL_NS else 0
        self._settime(seconds, nanoseconds, interval)
        self._next_ns, self._interval_ns, self.when = at, interval, when

    def _settime(self, seconds: int, nanoseconds: int, interval: int) -> None:
        spec = self._spec
        spec.it_value.tv_sec, spec.it_value.tv_nsec = seconds, nanoseconds
        spec.it_interval.tv_sec, spec.it_interval.tv_nsec = divmod(interval, 1_000_000_000)
        assert _LIBC is not None
        _LIBC.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None)

    def cancel(self) -> None:
        self.when = None
        if self._fd >= 0:
            self._armed = True
            self._next_ns, self._interval_ns = -1, 0
            self._settime(0, 0, 0)  # all zero: disarm
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
            expiries = int.from_bytes(os.read(self._fd, 8), sys.byteorder)
        except BlockingIOError:
            return  # re-armed after expiring: nothing due now
        if self._next_ns >= 0:  # after the first expiry due (the kernel may repeat it since)
            self._note_late((time.monotonic_ns() - self._next_ns) * 1e-9)
        interval = self._interval_ns
        if interval:  # the kernel has armed the next repetition already (past any missed)
            self._fired_ns = self._next_ns + (expiries - 1) * interval
            self._next_ns = self._fired_ns + interval
        else:
            self._fired_ns, self._next_ns = self._next_ns, -1
        self._armed = False
        try:
            self._fire()
        finally:
            self._fired_ns = -1
            if interval and not self._armed and self._fd >= 0:  # nobody wants the repetition
                self.cancel()

    def _fire_late(self) -> None:
        if self.when is not None:
            self._note_late(self.loop.time() - self.when)
        self._fire()

    def _note_late(self, late: float) -> None:
        if late > self.late_s:
            self.late_s = late

    def _fire(self) -> None:
        self.when = None
        self._handle = None
        self.callback()
