"""python-can's virtual bus read on the loop without a thread (scheduler/sources.py,
``VirtualSource``): a frame put in the bus's queue on any thread wakes a watching loop
once for a burst, by the cheap way when the sender is the loop itself; frames that came
unwatched wake it when it watches again; the bus's filters, a full queue and the bus's
shutdown behave as python-can's own queue would, but for a full queue, which refuses the
sender instead of blocking it. :func:`source_for` takes this source only for a virtual bus
laid out as it expects.

The loop is a fake that collects the wakes handed to it, and the other thread is joined
before anything is looked at: nothing here waits on time.
"""

from __future__ import annotations

import asyncio
import os
import queue
import threading
from collections.abc import Callable, Iterator
from typing import Any, cast

import can
import pytest
from can.interfaces import virtual

from abh3_supervisor.scheduler.sources import (
    FdSource,
    ThreadSource,
    VirtualSource,
    source_for,
)


class FakeLoop:
    """The loop as the source sees it: wakes queued (and how), run when the test says."""

    def __init__(self) -> None:
        self.queued: list[tuple[str, Callable[[], None]]] = []

    def call_soon(self, fn: Callable[[], None]) -> None:
        self.queued.append(("call_soon", fn))

    def call_soon_threadsafe(self, fn: Callable[[], None]) -> None:
        self.queued.append(("threadsafe", fn))

    def run(self) -> None:
        queued, self.queued = self.queued, []
        for _, fn in queued:
            fn()


def frame(ident: int) -> can.Message:
    return can.Message(arbitration_id=ident, is_extended_id=True, data=bytes(8))


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> Iterator[str]:
    name = f"vsource-{request.node.name}"
    yield name
    assert name not in virtual.channels  # every bus shut down: nothing of ours left behind


def read_on_loop(
    channel: str, before: Callable[[], None] = lambda: None, **bus_kwargs: Any
) -> tuple[VirtualSource, FakeLoop, list[str], can.BusABC]:
    """A virtual bus and its source; ``before`` runs between the two."""
    bus = can.Bus(interface="virtual", channel=channel, **bus_kwargs)
    before()
    loop, woken = FakeLoop(), cast(list[str], [])
    source = VirtualSource(
        cast(virtual.VirtualBus, bus),
        cast(asyncio.AbstractEventLoop, loop),
        lambda: woken.append("step"),
    )
    return source, loop, woken, bus


def drained(source: VirtualSource) -> list[int]:
    out = []
    while (got := source.recv()) is not None:
        out.append(got[0].arbitration_id)
    return out


def send_from_another_thread(channel: str, idents: list[int]) -> None:
    def run() -> None:
        with can.Bus(interface="virtual", channel=channel) as peer:
            for ident in idents:
                peer.send(frame(ident))

    sender = threading.Thread(target=run)
    sender.start()
    sender.join()


def test_a_burst_sent_on_another_thread_wakes_a_watching_loop_once(channel: str) -> None:
    source, loop, woken, bus = read_on_loop(channel)
    source.watch(True)
    send_from_another_thread(channel, [1, 2, 3])
    assert [how for how, _ in loop.queued] == ["threadsafe"]  # one wake for the burst
    loop.run()
    assert woken == ["step"] and drained(source) == [1, 2, 3]
    bus.shutdown()


def test_a_frame_sent_on_the_loops_own_thread_wakes_it_without_the_self_pipe(
    channel: str,
) -> None:
    source, loop, woken, bus = read_on_loop(channel)
    source.watch(True)
    with can.Bus(interface="virtual", channel=channel) as peer:  # the simulator's bus
        peer.send(frame(5))
        peer.send(frame(6))
    assert [how for how, _ in loop.queued] == ["call_soon"]
    loop.run()
    assert woken == ["step"] and drained(source) == [5, 6]
    bus.shutdown()


def test_frames_that_came_unwatched_wait_for_the_step_or_wake_the_loop_when_watched(
    channel: str,
) -> None:
    with can.Bus(interface="virtual", channel=channel) as peer:
        # frame 1 comes after the bus opened, before the pump started: kept
        source, loop, woken, bus = read_on_loop(channel, lambda: peer.send(frame(1)))
        peer.send(frame(2))
        assert loop.queued == []  # nobody watches: the next step reads them
        source.watch(True)
        loop.run()
        assert woken == ["step"] and drained(source) == [1, 2]
        source.watch(True)  # nothing waits: nothing to wake for
        assert loop.queued == []
        bus.shutdown()


def test_the_frames_the_bus_filters_refuse_are_read_past(channel: str) -> None:
    source, _, _, bus = read_on_loop(
        channel, can_filters=[{"can_id": 0x100, "can_mask": 0x7FF, "extended": True}]
    )
    with can.Bus(interface="virtual", channel=channel) as peer:
        for ident in (0x101, 0x100, 0x102, 0x100):
            peer.send(frame(ident))
    assert drained(source) == [0x100, 0x100]
    bus.shutdown()


def test_a_full_queue_refuses_the_sender_instead_of_blocking_it(channel: str) -> None:
    source, _, _, bus = read_on_loop(channel, rx_queue_size=1)
    with can.Bus(interface="virtual", channel=channel) as peer:
        peer.send(frame(1))
        with pytest.raises(can.CanOperationError):  # python-can's queue would block here
            peer.send(frame(2))
    assert drained(source) == [1]
    bus.shutdown()


def test_after_stop_no_wake_follows_and_the_bus_still_receives(channel: str) -> None:
    source, loop, woken, bus = read_on_loop(channel)
    source.watch(True)
    source.stop()
    send_from_another_thread(channel, [9])
    assert loop.queued == [] and woken == []
    assert bus.recv(0) is not None  # its queue, made a waking one, is still a queue
    bus.shutdown()


def test_a_shut_down_bus_leaves_the_channel_to_the_others(channel: str) -> None:
    source, _, _, bus = read_on_loop(channel)
    with (
        can.Bus(interface="virtual", channel=channel) as a,
        can.Bus(interface="virtual", channel=channel) as b,
    ):
        bus.shutdown()
        assert all(q is not source.bus.queue for q in virtual.channels[channel])
        a.send(frame(3))
        assert (got := b.recv(0)) is not None and got.arbitration_id == 3
    with pytest.raises(can.CanOperationError):  # the pump's read fails, and says so
        source.recv()


def test_a_sender_waiting_for_room_in_a_full_queue_is_let_in_by_the_step(channel: str) -> None:
    """A sender already inside python-can's own ``put`` of a full queue when the pump
    starts: the step's read makes room for it, as python-can's ``get`` would."""
    bus = cast(virtual.VirtualBus, can.Bus(interface="virtual", channel=channel, rx_queue_size=1))
    bus.queue.put(frame(1))
    waiting = threading.Thread(target=bus.queue.put, args=(frame(2),), daemon=True)
    waiting.start()  # blocks: the queue is full
    source = VirtualSource(bus, cast(asyncio.AbstractEventLoop, FakeLoop()), print)
    assert (got := source.recv()) is not None and got[0].arbitration_id == 1
    waiting.join(timeout=10)
    assert not waiting.is_alive()
    assert drained(source) == [2]
    bus.shutdown()


def test_another_reader_of_the_bus_is_served_as_python_can_serves_it(channel: str) -> None:
    source, _, _, bus = read_on_loop(channel)
    with can.Bus(interface="virtual", channel=channel) as peer:
        peer.send(frame(1))
        peer.send(frame(2))
    assert (got := bus.recv(0)) is not None and got.arbitration_id == 1
    assert drained(source) == [2] and bus.recv(0) is None
    bus.shutdown()


def test_a_stopped_source_gives_the_bus_its_own_queue_back(channel: str) -> None:
    source, _, _, bus = read_on_loop(channel)
    source.stop()
    assert type(source.bus.queue) is queue.Queue and not hasattr(source.bus.queue, "_arrived")
    assert VirtualSource.fits(bus)  # a next pump on it reads it the same way
    bus.shutdown()


class Subclassed(virtual.VirtualBus):
    """A virtual bus of somebody else's: its internals are not known to be python-can's."""


class WithFd(can.BusABC):
    def __init__(self, fd: int) -> None:
        super().__init__(channel="fd")
        self.fd = fd

    def fileno(self) -> int:
        return self.fd

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise AssertionError("never sent")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def test_source_for_picks_the_descriptor_the_virtual_queue_or_a_reader_thread(
    channel: str,
) -> None:
    async def pick(bus: can.BusABC) -> type:
        source = source_for(bus, asyncio.get_running_loop(), print, print, "b")
        source.stop()
        return type(source)

    plain = can.Bus(interface="virtual", channel=channel)
    other = Subclassed(channel=channel)
    moved = can.Bus(interface="virtual", channel=channel)
    moved.channel = []  # type: ignore[attr-defined]  # its queue is not where it is read
    rfd, wfd = os.pipe()
    try:
        assert asyncio.run(pick(plain)) is VirtualSource
        assert asyncio.run(pick(other)) is ThreadSource
        assert asyncio.run(pick(moved)) is ThreadSource
        assert asyncio.run(pick(WithFd(rfd))) is FdSource
    finally:
        moved.channel = virtual.channels[channel]  # type: ignore[attr-defined]
        for bus in (plain, other, moved):
            bus.shutdown()
        for fd in (rfd, wfd):
            os.close(fd)
