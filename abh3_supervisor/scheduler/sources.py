"""Where a pump's received frames wait until its next step reads them (scheduler/pump.py).

A bus with a file descriptor is its own queue: the step reads it with ``recv(0)``, and the
loop watches the descriptor when a frame should wake it. python-can's virtual bus (the
simulator's, the tests') hands each frame to a queue of ours on the sender's thread,
which the step reads. A bus with neither (most USB adapters) is read by a thread of its
own into a queue. All three wake the loop once for whatever came meanwhile, not once per
frame; :func:`source_for` picks one.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import queue
import select
import threading
import time
from collections.abc import Callable
from typing import Protocol, cast

import can
from can.interfaces import virtual

RECV_TIMEOUT_S = 0.05  # the reader thread's wait for a frame: how long stop() may take
RETRY_S = 0.5  # a bus whose receive failed is read again after this
WATCH_SET = hasattr(select, "epoll")  # FdSource's watch: an epoll set of its own
REFUSED_PER_RECV = 64  # frames the bus's own filters refuse, read past in one receive


class FrameSource(Protocol):
    def recv(self) -> tuple[can.Message, float | None] | None:
        """The next waiting frame and the wall time it was taken off the bus where the
        source knows it, or None (on the loop; the bus's receive may raise)."""
        ...

    def watch(self, on: bool) -> None:
        """Wake the loop (``wake``) when a frame waits, or leave the frames to the step."""
        ...

    def stop(self) -> None: ...


class FdSource:
    """The bus's own file descriptor: frames wait in the kernel.

    The pump turns the watch on and off twice per turn. Where there is epoll (Linux), the
    loop watches an epoll set of the source's own for good, and the watch puts the
    descriptor in that set or takes it out: one ``epoll_ctl``, where the loop's own
    ``add_reader``/``remove_reader`` cost about ten times as much (a handle made, the
    loop's selector updated) — on a small computer, 4 % of the bus loop at 100 turns a
    second. The set is level-triggered like the loop: a frame still waiting when the
    watch turns on wakes the loop at once. Unwatched, the descriptor leaves the set rather
    than staying in it with no events: epoll reports an error or a hang-up whatever the
    mask, and an unplugged adapter's descriptor would wake the loop on every turn."""

    def __init__(
        self, bus: can.BusABC, fd: int, loop: asyncio.AbstractEventLoop, wake: Callable[[], None]
    ) -> None:
        self.bus, self.fd, self.loop, self.wake = bus, fd, loop, wake
        self._watching = False
        # python-can's receive, read through its implementers' hook where the bus keeps
        # BusABC's own recv: a frame costs a few calls fewer (the step reads ~1000 a second)
        self._direct = type(bus).recv is can.BusABC.recv
        self._set: select.epoll | None = None
        if WATCH_SET:
            self._set = select.epoll()
            try:  # can epoll hold it? Out again until watched: a descriptor in the set
                self._set.register(fd, 0)  # reports an error or a hang-up whatever its
                self._set.unregister(fd)  # mask, and the loop would spin on it
            except OSError:  # a descriptor epoll refuses: the loop's own way, then
                self._set.close()
                self._set = None
            else:
                loop.add_reader(self._set.fileno(), wake)

    def recv(self) -> tuple[can.Message, float | None] | None:
        bus = self.bus
        if not self._direct:
            msg = bus.recv(0)
            return None if msg is None else (msg, None)  # the kernel's timestamp says when
        for _ in range(REFUSED_PER_RECV + 1):  # BusABC.recv(0) without its clock, its loop
            msg, filtered = bus._recv_internal(0)  # and its debug log
            if msg is None:
                return None
            if filtered or bus._matches_filters(msg):
                return msg, None
            # one the bus's filters refuse: the next, where recv(0) would end the read
        return None  # a flood of refused frames: the rest waits for the next step

    def watch(self, on: bool) -> None:
        if on == self._watching:
            return
        if self._set is not None:
            if on:
                self._set.register(self.fd, select.EPOLLIN)
            else:
                with contextlib.suppress(OSError):  # closed under us: the kernel dropped it
                    self._set.unregister(self.fd)
        elif on:
            self.loop.add_reader(self.fd, self.wake)
        else:
            self.loop.remove_reader(self.fd)
        self._watching = on

    def stop(self) -> None:
        try:
            self.watch(False)
        finally:
            if self._set is not None:
                self.loop.remove_reader(self._set.fileno())
                self._set.close()
                self._set = None


class _HandOver:
    """Frames kept for the loop's step, and the one wake on its way to the loop for them:
    watched, a source wakes the loop once for whatever comes meanwhile (a late loop gets
    one call for a burst of frames); unwatched, the frames wait for the next step."""

    def __init__(self, loop: asyncio.AbstractEventLoop, wake: Callable[[], None]) -> None:
        self.loop, self.wake = loop, wake
        self._watching = False
        self._waking = False  # a wake is on its way to the loop
        self._stopped = threading.Event()
        self._loop_thread = threading.get_ident()  # made on the loop (the pump's start)

    def _waiting(self) -> bool:
        """Whether frames wait for the step."""
        raise NotImplementedError

    def watch(self, on: bool) -> None:
        self._watching = on
        if on and self._waiting():  # came while nobody watched
            self._wake_once()

    def _wake_once(self) -> None:  # from any thread
        if not self._waking and not self._stopped.is_set():
            self._waking = True
            self._to_loop(self._woken)

    def _woken(self) -> None:  # on the loop
        self._waking = False
        if not self._stopped.is_set():
            self.wake()

    def _to_loop(self, fn: Callable[..., None], *args: object) -> None:
        """``fn`` on the loop, soon: without the self-pipe from the loop's own thread."""
        try:
            if threading.get_ident() == self._loop_thread:
                self.loop.call_soon(fn, *args)
            else:
                self.loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the loop closed (a pump nobody stopped): the run is over
            self._stopped.set()


class ThreadSource(_HandOver):
    """A reader thread's queue, handed over to the loop as :class:`_HandOver` does. A
    receive that fails is told to the loop (``on_error``) and tried again after
    ``RETRY_S``: the thread never dies of it (python-can's Notifier's thread did, when
    it ran for a loop, and the bus went deaf for the rest of the run). Each frame keeps
    the wall time the thread took it: an interface whose own timestamps are not the wall
    clock (PCAN's since boot, a drifting hardware clock) is still timed when it came,
    not when the step reads it."""

    def __init__(
        self,
        bus: can.BusABC,
        loop: asyncio.AbstractEventLoop,
        wake: Callable[[], None],
        on_error: Callable[[Exception], None],
        name: str,
    ) -> None:
        super().__init__(loop, wake)
        self.bus, self.on_error = bus, on_error
        self._frames: collections.deque[tuple[can.Message, float]] = collections.deque()
        self._thread = threading.Thread(target=self._run, name=f"can reader {name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def recv(self) -> tuple[can.Message, float | None] | None:
        try:
            return self._frames.popleft()
        except IndexError:
            return None

    def _waiting(self) -> bool:
        return bool(self._frames)

    def stop(self) -> None:
        self._watching = False
        self._stopped.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)

    def _failed(self, exc: Exception) -> None:  # on the loop
        if not self._stopped.is_set():  # a pump stopped meanwhile hears of it no more
            self.on_error(exc)

    def _run(self) -> None:
        while not self._stopped.is_set():
            try:
                msg = self.bus.recv(RECV_TIMEOUT_S)
            except Exception as exc:  # whatever the interface raises: say so, rest, again
                self._to_loop(self._failed, exc)
                self._stopped.wait(RETRY_S)
                continue
            if msg is None:
                continue
            self._frames.append((msg, time.time()))
            if self._watching:
                self._wake_once()


class VirtualSource(_HandOver):
    """python-can's virtual bus, read on the loop: no thread of its own.

    The virtual bus hands each frame to every other bus of its channel by putting it in
    that bus's queue, on the sender's thread. While the pump runs, the source makes its
    bus's queue a :class:`_WakingQueue` (the same object: a sender already on its way to
    it, on another thread, still finds it), whose ``put`` hands the frame over as
    :class:`_HandOver` does: a plain ``call_soon`` when the sender is the loop itself
    (``abh3 run``'s simulated drives), else ``call_soon_threadsafe``. A reader thread
    would cost a thread, and on the loop the same wake-up (docs/performance.md, section
    2). The step takes the frames off with the queue's own ``get_nowait`` (under its
    lock: another reader of the bus, a sender waiting for room, are served as before).
    A full queue (the bus's ``rx_queue_size``) refuses the frame — the sender's ``send``
    fails — where python-can's own would block the sender, which may be this loop. A
    sender already inside the queue's ``put`` when the pump starts wakes nobody: its
    frame is read by the next step, as one that came unwatched."""

    def __init__(
        self, bus: virtual.VirtualBus, loop: asyncio.AbstractEventLoop, wake: Callable[[], None]
    ) -> None:
        super().__init__(loop, wake)
        self.bus = bus
        self._frames = bus.queue
        self._frames._arrived = self._arrived  # type: ignore[attr-defined]
        self._frames.__class__ = _WakingQueue  # what it holds (sent before the start) stays

    @staticmethod
    def fits(bus: can.BusABC) -> bool:
        """A virtual bus laid out as this python-can's: a plain queue, in its channel's
        list of the queues a send puts each frame in."""
        return (
            type(bus) is virtual.VirtualBus
            and type(getattr(bus, "queue", None)) is queue.Queue
            and any(q is bus.queue for q in getattr(bus, "channel", ()))
        )

    def recv(self) -> tuple[can.Message, float | None] | None:
        bus, frames = self.bus, self._frames
        bus._check_if_open()  # shut down under the pump: a receive that fails, told
        for _ in range(REFUSED_PER_RECV + 1):
            try:
                msg = frames.get_nowait()
            except queue.Empty:
                return None
            if bus._matches_filters(msg):
                return msg, None  # its timestamp: the wall time it was sent
        return None  # a flood of refused frames: the rest waits for the next step

    def _waiting(self) -> bool:
        return bool(self._frames.qsize())

    def stop(self) -> None:
        """The bus's queue is python-can's own again (the bus may outlive the pump)."""
        self._watching = False
        self._stopped.set()
        frames = self._frames
        if isinstance(frames, _WakingQueue):
            del frames._arrived
            frames.__class__ = queue.Queue  # type: ignore[assignment]  # the same object

    def _arrived(self) -> None:  # on the sender's thread
        if self._watching:
            self._wake_once()


class _WakingQueue(queue.Queue[can.Message]):
    """A virtual bus's receive queue that says when a frame came (``_arrived``, set
    before a queue becomes one), and never blocks."""

    _arrived: Callable[[], None]

    def put(self, item: can.Message, block: bool = True, timeout: float | None = None) -> None:
        super().put(item, block=False)  # full: queue.Full, the sender's send fails
        self._arrived()


def source_for(
    bus: can.BusABC,
    loop: asyncio.AbstractEventLoop,
    wake: Callable[[], None],
    on_error: Callable[[Exception], None],
    name: str,
) -> FrameSource:
    """Where ``bus``'s frames wait: its file descriptor, a virtual bus's queue, or a
    reader thread's (started)."""
    try:
        fd = bus.fileno()
    except NotImplementedError:  # python-can's virtual bus, some USB adapters
        fd = -1
    if fd >= 0:
        return FdSource(bus, fd, loop, wake)
    if VirtualSource.fits(bus):
        return VirtualSource(cast(virtual.VirtualBus, bus), loop, wake)
    reader = ThreadSource(bus, loop, wake, on_error, name)
    reader.start()
    return reader
