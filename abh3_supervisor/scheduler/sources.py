"""How a pump reads its bus: python-can's model, and only its public calls.

A bus with a file descriptor (``bus.fileno()``: SocketCAN, ``udp_multicast``, the
in-process simulator's drives' bus) is read on the loop with its own ``recv(0)``, and the
loop watches the descriptor while a frame should wake it (:class:`FdReader`). Any other
bus (most USB adapters, python-can's ``virtual`` bus) is read by a thread of its own into
a queue (:class:`ThreadReader`), which wakes the loop once for whatever came meanwhile,
not once per frame. :func:`source_for` picks one; the pump reads either with ``take(0)``
until it gives None.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import select
import threading
import time
from collections.abc import Callable
from typing import Protocol

import can

RECV_TIMEOUT_S = 0.05  # the reader thread's wait for a frame: how long stop() may take
RETRY_S = 0.5  # a bus whose receive failed is read again after this
WATCH_SET = hasattr(select, "epoll")  # FdReader's watch: an epoll set of its own


class FrameSource(Protocol):
    take: Callable[[float], can.Message | None]
    """``take(0)``: the next frame waiting, or None (on the loop; it may raise)."""
    arrived: float | None
    """The wall time the frame ``take`` last gave was taken off the bus, where the source
    knows it (a reader thread does; a descriptor's frames carry the kernel's time)."""

    def watch(self, on: bool) -> None:
        """Wake the loop (``wake``) when a frame waits, or leave the frames to the step."""
        ...

    def stop(self) -> None: ...

    def recv(self) -> tuple[can.Message, float | None] | None:
        """The next frame and ``arrived``, or None."""
        ...


class _Recv:
    take: Callable[[float], can.Message | None]  # the bus's own recv, or the queue's
    arrived: float | None = None

    def recv(self) -> tuple[can.Message, float | None] | None:
        msg = self.take(0)
        return None if msg is None else (msg, self.arrived)


class FdReader(_Recv):
    """The bus's own descriptor, read with the bus's own ``recv(0)``.

    The pump turns the watch on and off about once a turn. Where there is epoll (Linux),
    the loop watches an epoll set of the reader's own for good, and the watch puts the
    descriptor in that set or takes it out: one ``epoll_ctl``, where the loop's
    ``add_reader``/``remove_reader`` cost about ten times as much. Level-triggered like
    the loop: a frame waiting when the watch turns on wakes the loop at once. Unwatched,
    the descriptor leaves the set: epoll reports an error or a hang-up whatever the mask,
    and an unplugged adapter would wake the loop on every turn."""

    def __init__(
        self, bus: can.BusABC, fd: int, loop: asyncio.AbstractEventLoop, wake: Callable[[], None]
    ) -> None:
        self.take = bus.recv
        self.fd, self.loop, self.wake = fd, loop, wake
        self.watching = False
        self.set: select.epoll | None = None
        if WATCH_SET:
            self.set = select.epoll()
            try:  # can epoll hold it? Out again until watched
                self.set.register(fd, 0)
                self.set.unregister(fd)
            except OSError:  # a descriptor epoll refuses (a regular file): the loop's way
                self.set.close()
                self.set = None
            else:
                loop.add_reader(self.set.fileno(), wake)

    def watch(self, on: bool) -> None:
        if on == self.watching:
            return
        if self.set is None:
            if on:
                self.loop.add_reader(self.fd, self.wake)
            else:
                self.loop.remove_reader(self.fd)
        elif on:
            self.set.register(self.fd, select.EPOLLIN)
        else:
            with contextlib.suppress(OSError):  # closed under us: the kernel dropped it
                self.set.unregister(self.fd)
        self.watching = on

    def stop(self) -> None:
        try:
            self.watch(False)
        finally:
            if self.set is not None:
                self.loop.remove_reader(self.set.fileno())
                self.set.close()
                self.set = None


class ThreadReader(_Recv):
    """A reader thread's queue. Watched, the first frame of a burst hands one wake to the
    loop; frames that came unwatched wake it when the watch turns on. A receive that
    fails is told to the loop (``on_error``) and tried again after ``RETRY_S``: the
    thread never dies of it (python-can's Notifier's did, and the bus went deaf for the
    rest of the run). Each frame keeps the wall time the thread took it (``arrived``): an
    interface whose timestamps are not the wall clock is still timed when it came."""

    def __init__(
        self,
        bus: can.BusABC,
        loop: asyncio.AbstractEventLoop,
        wake: Callable[[], None],
        on_error: Callable[[Exception], None],
        name: str,
    ) -> None:
        self.bus, self.loop, self.wake, self.on_error = bus, loop, wake, on_error
        self.take = self.pop
        self.frames: collections.deque[tuple[can.Message, float]] = collections.deque()
        self.watching = False
        self.waking = False  # a wake is on its way to the loop
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self.run, name=f"can reader {name}", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def pop(self, timeout: float = 0.0) -> can.Message | None:
        try:
            msg, self.arrived = self.frames.popleft()
        except IndexError:
            return None
        return msg

    def watch(self, on: bool) -> None:  # on the loop
        self.watching = on
        if on and self.frames:  # came while nobody watched
            self.wake_once(self.loop.call_soon)

    def wake_once(self, call: Callable[[Callable[[], None]], object]) -> None:
        if not self.waking and not self.stopped.is_set():
            self.waking = True
            self.hand(call, self.woken)

    def woken(self) -> None:  # on the loop
        self.waking = False
        if not self.stopped.is_set():
            self.wake()

    def hand(self, call: Callable[..., object], fn: Callable[..., None], *args: object) -> None:
        try:
            call(fn, *args)
        except RuntimeError:  # the loop closed (a pump nobody stopped): the run is over
            self.stopped.set()

    def failed(self, exc: Exception) -> None:  # on the loop
        if not self.stopped.is_set():  # a pump stopped meanwhile hears of it no more
            self.on_error(exc)

    def stop(self) -> None:
        self.watching = False
        self.stopped.set()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout=1.0)

    def run(self) -> None:
        while not self.stopped.is_set():
            try:
                msg = self.bus.recv(RECV_TIMEOUT_S)
            except Exception as exc:  # whatever the interface raises: say so, rest, again
                self.hand(self.loop.call_soon_threadsafe, self.failed, exc)
                self.stopped.wait(RETRY_S)
                continue
            if msg is not None:
                self.frames.append((msg, time.time()))
                if self.watching:
                    self.wake_once(self.loop.call_soon_threadsafe)


def source_for(
    bus: can.BusABC,
    loop: asyncio.AbstractEventLoop,
    wake: Callable[[], None],
    on_error: Callable[[Exception], None],
    name: str,
) -> FrameSource:
    """Where ``bus``'s frames wait: its file descriptor, or a reader thread's queue
    (started)."""
    try:
        fd = bus.fileno()
    except NotImplementedError:  # python-can's virtual bus, some USB adapters
        fd = -1
    if fd >= 0:
        return FdReader(bus, fd, loop, wake)
    reader = ThreadReader(bus, loop, wake, on_error, name)
    reader.start()
    return reader
