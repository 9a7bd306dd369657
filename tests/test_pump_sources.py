"""How a pump reads its bus (scheduler/sources.py), python-can's way. A bus without a file
descriptor is read by a thread into a queue: a burst of frames wakes the loop once, frames
that came while nobody watched wake it when it watches again, and a receive that fails is
told and tried again, never the thread's end. A bus with one is read with its own
``recv(0)``, and watched through an epoll set the loop watches for good.

The reader's body runs in the test's own thread over a scripted bus, and the loop is a
fake that collects what the thread hands it: nothing here waits on time.
"""

from __future__ import annotations

import asyncio
import select
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import can
import pytest

from abh3_supervisor.scheduler import sources
from abh3_supervisor.scheduler.sources import ThreadReader


class HandOver:
    """The loop as the reader thread sees it: callbacks queued, run when the test says."""

    def __init__(self) -> None:
        self.queued: list[tuple[Callable[..., None], tuple[Any, ...]]] = []

    def call_soon_threadsafe(self, fn: Callable[..., None], *args: Any) -> None:
        self.queued.append((fn, args))

    call_soon = call_soon_threadsafe  # the test's thread plays the reader's and the loop's

    def run(self) -> None:
        queued, self.queued = self.queued, []
        for fn, args in queued:
            fn(*args)


class Scripted(can.BusABC):
    """Hands out its script one item per receive (a frame, None, or an error to raise),
    and ends the reader when the script is done."""

    def __init__(self, script: list[can.Message | Exception | None]) -> None:
        super().__init__(channel="scripted")
        self.script = script
        self.source: ThreadReader | None = None
        self.waits: list[float] = []

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self.script:
            assert self.source is not None
            self.source.stopped.set()
            return None, False
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise AssertionError("the reader never sends")


def reader(
    script: list[can.Message | Exception | None], watching: bool
) -> tuple[ThreadReader, HandOver, list[str], list[Exception], Scripted]:
    loop, woken, errors = HandOver(), [], cast(list[Exception], [])
    bus = Scripted(script)
    source = ThreadReader(
        bus, cast(asyncio.AbstractEventLoop, loop), lambda: woken.append("step"), errors.append, "t"
    )
    bus.source = source
    source.watch(watching)
    return source, loop, woken, errors, bus


def read_script(source: ThreadReader) -> None:
    """The reader thread's body until the script ends (which stops it); then the source
    is live again, as though the thread went on waiting."""
    source.run()
    source.stopped.clear()


def frame(ident: int) -> can.Message:
    return can.Message(arbitration_id=ident, is_extended_id=True, data=bytes(8))


def drained(source: ThreadReader) -> list[int]:
    out = []
    while (got := source.recv()) is not None:
        out.append(got[0].arbitration_id)
    return out


def test_a_burst_of_frames_wakes_a_watching_loop_once() -> None:
    source, loop, woken, _, bus = reader([frame(1), frame(2), None, frame(3)], watching=True)
    read_script(source)
    assert len(loop.queued) == 1  # one wake on its way for the whole burst
    loop.run()
    assert woken == ["step"] and drained(source) == [1, 2, 3]
    bus.shutdown()


def test_frames_that_came_unwatched_wake_the_loop_when_it_watches_again() -> None:
    source, loop, woken, _, bus = reader([frame(1), frame(2)], watching=False)
    read_script(source)
    assert loop.queued == []  # the step due within batch_s reads them
    source.watch(True)  # the step did not come (or did not read them all): wake now
    loop.run()
    assert woken == ["step"] and drained(source) == [1, 2]
    source.watch(True)  # nothing waits: nothing to wake for
    assert loop.queued == []
    bus.shutdown()


def test_a_receive_that_fails_is_told_then_tried_again_after_a_rest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    down = can.CanOperationError("Network is down")
    source, loop, woken, errors, bus = reader([down, frame(7)], watching=True)
    rests: list[float | None] = []
    monkeypatch.setattr(source.stopped, "wait", rests.append)
    read_script(source)
    loop.run()
    assert errors == [down] and rests == [sources.RETRY_S]
    assert woken == ["step"] and drained(source) == [7]  # read again after the rest
    bus.shutdown()


def test_stop_ends_the_thread_and_no_wake_follows() -> None:
    bus = can.Bus(interface="virtual", channel="sources-stop")
    loop, woken = HandOver(), []
    source = ThreadReader(
        bus, cast(asyncio.AbstractEventLoop, loop), lambda: woken.append("step"), print, "v"
    )
    source.start()
    source.watch(True)
    source.stop()
    assert not source.thread.is_alive()
    source.frames.append((frame(1), 0.0))
    source.waking = False
    source.watch(True)  # a wake already queued when the pump stopped
    loop.run()
    assert woken == []
    bus.shutdown()


def test_a_failed_receive_is_not_told_to_a_pump_stopped_meanwhile() -> None:
    source, loop, _, errors, bus = reader([can.CanOperationError("down")], watching=True)
    source.stopped.wait = lambda timeout=None: True  # type: ignore[method-assign]
    read_script(source)
    source.stop()  # the pump stopped before the loop ran the hand-over
    loop.run()
    assert errors == []
    bus.shutdown()


def test_the_reader_ends_when_the_loop_is_gone() -> None:
    """A pump nobody stopped: its loop closed, its bus shut down, every receive fails;
    the thread ends instead of retrying for ever."""

    class Closed(HandOver):
        def call_soon_threadsafe(self, fn: Callable[..., None], *args: Any) -> None:
            raise RuntimeError("Event loop is closed")

        call_soon = call_soon_threadsafe

    bus = Scripted([can.CanOperationError("bus shut down")] * 3)
    source = ThreadReader(bus, cast(asyncio.AbstractEventLoop, Closed()), print, print, "c")
    bus.source = source
    source.run()
    assert source.stopped.is_set() and len(bus.script) == 2  # one try, then the end
    bus.shutdown()


class Socket(can.BusABC):
    """A descriptor that can be made readable at will (one end of a socket pair)."""

    def __init__(self) -> None:
        super().__init__(channel="s")
        self.ours, self.theirs = socket.socketpair()

    def fileno(self) -> int:
        return self.ours.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise NotImplementedError

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False

    def shutdown(self) -> None:
        super().shutdown()
        self.ours.close()
        self.theirs.close()


def readable(fd: int) -> bool:
    return bool(select.select([fd], [], [], 0)[0])


@pytest.mark.skipif(not sources.WATCH_SET, reason="no epoll on this system")
def test_the_fd_watch_is_an_epoll_set_the_loop_watches_for_good() -> None:
    """Watching on and off changes the set, never the loop's readers; a frame waiting
    makes the set readable only while watched, and one that waited before the watch
    turned on makes it readable at once."""
    bus = Socket()
    loop = asyncio.new_event_loop()
    woken: list[int] = []
    try:
        source = sources.FdReader(bus, bus.fileno(), loop, lambda: woken.append(1))
        assert source.set is not None
        watched = source.set.fileno()
        selector = loop._selector  # type: ignore[attr-defined]
        assert set(selector.get_map()) >= {watched} and bus.fileno() not in selector.get_map()
        bus.theirs.send(b"x")  # a frame waits, unwatched
        assert not readable(watched)
        source.watch(True)
        assert readable(watched)  # what waited wakes the loop at once
        loop.run_until_complete(asyncio.sleep(0))  # one turn: the loop sees the set readable
        assert woken
        source.watch(False)
        assert not readable(watched)
        source.stop()
        assert watched not in selector.get_map()
    finally:
        loop.close()
        bus.shutdown()


def test_a_descriptor_epoll_refuses_is_watched_the_loop_s_way(tmp_path: Path) -> None:
    """A regular file cannot join an epoll set (EPERM): its watch is the loop's reader."""
    readers: dict[int, Callable[[], None]] = {}

    class Loop:
        def add_reader(self, fd: int, callback: Callable[[], None]) -> None:
            readers[fd] = callback

        def remove_reader(self, fd: int) -> None:
            del readers[fd]

    bus = Socket()
    try:
        with (tmp_path / "f").open("wb") as f:
            source = sources.FdReader(bus, f.fileno(), cast(Any, Loop()), print)
            assert source.set is None
            source.watch(True)
            assert list(readers) == [f.fileno()]
            source.stop()
            assert readers == {}
    finally:
        bus.shutdown()


class Filtered(Socket):
    """Hands out its frames one per receive, unfiltered: the bus's filters decide."""

    def __init__(self, ids: list[int]) -> None:
        super().__init__()
        self.frames = [can.Message(arbitration_id=i, is_extended_id=True) for i in ids]

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.frames.pop(0) if self.frames else None), False


def test_a_descriptor_is_read_with_the_bus_s_own_receive() -> None:
    """python-can's ``recv(0)``, filters and all: a frame they refuse ends that read (the
    descriptor stays readable: the rest is read at the next wake or step)."""
    bus = Filtered([0x1, 0x2, 0x3, 0x2])
    bus.set_filters([{"can_id": 0x2, "can_mask": 0x1FFFFFFF, "extended": True}])
    loop = asyncio.new_event_loop()
    try:
        source = sources.FdReader(bus, bus.fileno(), loop, print)
        taken = [source.take(0) for _ in range(4)]
        assert [m.arbitration_id if m else None for m in taken] == [None, 0x2, None, 0x2]
        assert source.recv() is None and source.arrived is None  # the kernel's time says
        source.stop()
    finally:
        loop.close()
        bus.shutdown()


async def turns(n: int) -> None:
    for _ in range(n):
        await asyncio.sleep(0)


@pytest.mark.skipif(not sources.WATCH_SET, reason="no epoll on this system")
def test_an_unwatched_hung_up_descriptor_never_wakes_the_loop() -> None:
    """epoll reports a hang-up or an error whatever the mask, even none: unwatched, the
    descriptor is out of the set, as it was out of the loop (an unplugged adapter, a peer
    gone), and the loop sleeps instead of stepping the pump on every turn."""
    bus = Socket()
    loop = asyncio.new_event_loop()
    woken: list[int] = []
    try:
        source = sources.FdReader(bus, bus.fileno(), loop, lambda: woken.append(1))
        source.watch(True)
        source.watch(False)
        bus.theirs.shutdown(socket.SHUT_RDWR)  # a hang-up on ours
        bus.ours.shutdown(socket.SHUT_RDWR)
        loop.run_until_complete(turns(100))
        assert woken == []
        source.stop()
    finally:
        loop.close()
        bus.shutdown()


@pytest.mark.skipif(not sources.WATCH_SET, reason="no epoll on this system")
def test_unwatching_a_descriptor_closed_under_the_source_is_silent() -> None:
    """As the loop's ``remove_reader`` was: the kernel dropped it from the set already."""
    bus = Socket()
    loop = asyncio.new_event_loop()
    try:
        source = sources.FdReader(bus, bus.fileno(), loop, print)
        assert source.set is not None
        watched = source.set.fileno()
        source.watch(True)
        bus.ours.close()
        source.stop()
        assert watched not in loop._selector.get_map()  # type: ignore[attr-defined]
    finally:
        loop.close()
        bus.shutdown()
