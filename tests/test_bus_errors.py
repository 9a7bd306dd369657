"""Bus errors on real interfaces: bus-off, error-passive, a full transmit queue — found in
python-can's error frames and exceptions, reported per bus, and recovered from."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import queue
import socket
from collections.abc import Iterator
from typing import Any, ClassVar

import can
import pytest

from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui import overview
from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.scheduler import bus_health as bh
from abh3_supervisor.scheduler.bus_health import BusHealth, BusState
from abh3_supervisor.service import snapshot
from tests.support.buses import BusNotices, drives_on


def error_frame(cls: int, crtl: int = 0, tx: int = 0, rx: int = 0) -> tuple[int, bytes]:
    return cls, bytes([0, crtl, 0, 0, 0, 0, tx, rx])


def state(h: BusHealth) -> BusState:  # read afresh: each call can change it
    return h.state


def test_error_frames_and_send_errors_drive_the_state() -> None:
    h = BusHealth("b")
    h.on_error_frame(*error_frame(bh.ERR_CRTL, bh.CRTL_TX_WARNING, tx=100), now=1.0)
    assert state(h) is BusState.WARNING and "tx errors 100" in h.detail
    h.on_error_frame(*error_frame(bh.ERR_CRTL | bh.ERR_CNT, bh.CRTL_TX_PASSIVE, tx=130), now=2.0)
    assert state(h) is BusState.PASSIVE
    h.on_received(now=6.9)  # frames arrive, but an error frame came less than 5 s ago
    assert state(h) is BusState.PASSIVE
    h.on_received(now=7.0)
    assert state(h) is BusState.OK and h.since == 7.0
    h.on_error_frame(*error_frame(bh.ERR_BUSOFF), now=8.0)
    assert state(h) is BusState.BUS_OFF
    h.on_error_frame(*error_frame(bh.ERR_RESTARTED), now=9.0)
    assert state(h) is BusState.OK
    h.on_send_error(errno.ENOBUFS, "No buffer space available", now=10.0)
    assert state(h) is BusState.TX_FULL
    h.on_received(now=10.1)  # traffic, but nothing of ours went out yet
    assert state(h) is BusState.TX_FULL
    h.on_sent(now=10.2)
    h.on_received(now=10.3)
    assert state(h) is BusState.OK
    h.on_send_error(None, "wacousb /dev/ttyACM0: transmit stalled: …", now=10.4)
    assert state(h) is BusState.TX_FULL and "stalled" in h.detail
    h.on_sent(now=10.5)
    h.on_received(now=10.6)
    h.on_send_error(errno.ENETDOWN, "Network is down", now=11.0)
    assert state(h) is BusState.BUS_OFF
    h.on_send_error(None, "whatever", now=11.5)  # still bus-off: not demoted to "failing"
    assert state(h) is BusState.BUS_OFF
    h.on_error_frame(*error_frame(bh.ERR_CRTL, bh.CRTL_ACTIVE), now=12.0)
    assert state(h) is BusState.BUS_OFF  # "active" ends warning/passive, not a bus-off
    assert [(c.old, c.new) for c in h.drain()] == [
        (BusState.OK, BusState.WARNING),
        (BusState.WARNING, BusState.PASSIVE),
        (BusState.PASSIVE, BusState.OK),
        (BusState.OK, BusState.BUS_OFF),
        (BusState.BUS_OFF, BusState.OK),
        (BusState.OK, BusState.TX_FULL),
        (BusState.TX_FULL, BusState.OK),
        (BusState.OK, BusState.TX_FULL),
        (BusState.TX_FULL, BusState.OK),
        (BusState.OK, BusState.BUS_OFF),
    ]
    assert h.error_frames == 5


class FlakyBus(can.BusABC):
    """A python-can bus (on a virtual channel) whose sends raise and which delivers error
    frames when told to: what SocketCAN does on a real bus in trouble."""

    instances: ClassVar[list[FlakyBus]] = []

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.fail: can.CanError | None = None
        self.recv_fail: can.CanError | None = None  # an adapter unplugged, say
        self.errors: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self.channel_info = f"flaky {channel}"
        super().__init__(channel=channel)
        FlakyBus.instances.append(self)

    def inject(self, cls: int, data: bytes) -> None:
        self.errors.put(can.Message(arbitration_id=cls, data=data, is_error_frame=True))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail is not None:
            raise self.fail
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.recv_fail is not None:
            raise self.recv_fail
        try:
            return self.errors.get_nowait(), False
        except queue.Empty:
            pass
        return self.inner.recv(0.005 if timeout is None else min(timeout, 0.005)), False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


class FdBus(FlakyBus):
    """As SocketCAN: a file descriptor the pump reads on the loop (``add_reader``, its
    ``FdSource``), and a receive that raises when the interface goes down."""

    def __init__(self, channel: Any = None, **kwargs: Any) -> None:
        super().__init__(channel, **kwargs)
        self._r, self._w = socket.socketpair()
        self._r.setblocking(False)
        self.down = False
        self.reads = 0

    def fileno(self) -> int:
        return self._r.fileno()

    def go_down(self) -> None:
        self.down = True
        self._w.send(b"!")  # readable: the loop calls recv, which fails

    def go_up(self) -> None:
        self.down = False
        with contextlib.suppress(BlockingIOError):
            self._r.recv(64)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self.reads += 1
        if self.down:
            raise can.CanOperationError("Error receiving: Network is down", errno.ENETDOWN)
        return None, False

    def shutdown(self) -> None:
        super().shutdown()
        self._r.close()
        self._w.close()


@pytest.fixture
def flaky(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setitem(can.interfaces.BACKENDS, "flaky", (__name__, "FlakyBus"))
    monkeypatch.setitem(can.interfaces.BACKENDS, "fdflaky", (__name__, "FdBus"))
    valid = can.interfaces.VALID_INTERFACES | {"flaky", "fdflaky"}
    monkeypatch.setattr(can.util, "VALID_INTERFACES", valid)
    FlakyBus.instances.clear()
    yield
    FlakyBus.instances.clear()


@pytest.mark.wallclock
def test_the_supervisor_reports_bus_errors_per_bus_and_recovers(flaky: None) -> None:
    config = parse_config(
        "buses:\n  robot: {interface: flaky, channel: errs}\nunits:\n  - {name: base}\n", "e.yaml"
    )
    notices = BusNotices("robot")

    async def scenario() -> None:
        with drives_on(config, "robot", "errs"):
            async with Runtime(config) as rt:
                sup = rt.supervisor
                sup.subscribe(notices)
                assert await sup.wait_exchange("base", sup.clock(), 3.0)
                (bus,) = FlakyBus.instances
                health = sup.bus_health["robot"]

                bus.inject(*error_frame(bh.ERR_BUSOFF))
                assert "BUS-OFF" in await notices.next() and state(health) is BusState.BUS_OFF
                screen = overview.render(mirrored(rt), ["base"], 0, 120).plain
                assert "bus robot: BUS-OFF for 0 s: the controller went bus-off" in screen
                bus.inject(*error_frame(bh.ERR_RESTARTED))
                assert "recovered from bus-off" in await notices.next()

                bus.fail = can.CanOperationError(
                    "Failed to transmit: No buffer space", errno.ENOBUFS
                )
                assert "TX QUEUE FULL" in await notices.next()
                assert await sup.wait_exchange("base", sup.clock(), 0.3) is False  # nothing goes
                bus.fail = None
                assert "recovered from tx queue full" in await notices.next()
                assert await sup.wait_exchange("base", sup.clock(), 1.0)  # and the unit answers

                bus.inject(*error_frame(bh.ERR_CRTL | bh.ERR_CNT, bh.CRTL_RX_PASSIVE, rx=140))
                assert "ERROR-PASSIVE" in await notices.next()
                bus.inject(*error_frame(bh.ERR_CRTL | bh.ERR_CNT, bh.CRTL_ACTIVE, rx=20))
                assert "recovered from error-passive" in await notices.next()
                assert "bus robot" not in overview.render(mirrored(rt), ["base"], 0, 120).plain
        assert rt.stops_confirmed

    asyncio.run(scenario())
    # the fake bus keeps carrying frames while "bus-off": under load the traffic may
    # prove the recovery before the injected restart frame does; either is a recovery
    assert notices.seen[1] in (
        "bus robot: recovered from bus-off: the controller restarted",
        "bus robot: recovered from bus-off: frames go out and come in again",
    )
    assert notices.seen[:1] + notices.seen[2:] == [
        "bus robot: BUS-OFF: the controller went bus-off",
        "bus robot: TX QUEUE FULL: the transmit queue is full (no node acks?)",
        "bus robot: recovered from tx queue full: frames go out and come in again",
        "bus robot: ERROR-PASSIVE: error-passive (tx errors 0, rx errors 140)",
        "bus robot: recovered from error-passive: the controller is error-active again (tx errors 0, rx errors 20)",
    ]


@pytest.mark.wallclock
def test_a_bus_without_a_descriptor_whose_receive_fails_is_heard_again_when_it_comes_back(
    flaky: None,
) -> None:
    """A USB adapter's receive failing for a moment: the pump's reader thread says so,
    rests and reads again (python-can's Notifier's thread died of it, and the drives went
    unheard for the rest of the run). The drive side judges: it goes on getting our
    commands, answers, and its answers to the stop frames are heard at the end."""
    config = parse_config(
        "buses:\n  robot: {interface: flaky, channel: rxfail}\nunits:\n  - {name: base}\n",
        "e.yaml",
    )
    notices = BusNotices("robot")

    async def scenario() -> None:
        with drives_on(config, "robot", "rxfail") as drives:
            async with Runtime(config) as rt:
                sup = rt.supervisor
                sup.subscribe(notices)
                assert await sup.wait_exchange("base", sup.clock(), 3.0)
                (bus,) = FlakyBus.instances
                bus.recv_fail = can.CanOperationError("Error receiving: device gone", errno.ENODEV)
                assert "receive failed" in await notices.next()
                bus.recv_fail = None
                heard = drives.frames_received
                assert await sup.wait_exchange("base", sup.clock(), 3.0)  # answers heard again
                assert drives.frames_received > heard  # and the drive gets our commands
        assert rt.stops_confirmed

    asyncio.run(scenario())
    assert notices.seen == [
        "bus robot: SENDS FAILING: receive failed: Error receiving: device gone [Error Code 19]",
        "bus robot: recovered from sends failing: frames go out and come in again",
    ]


def mirrored(rt: Runtime) -> Mirror:
    """What a TUI attached to this runtime would show."""
    mirror = Mirror.of(rt.config)
    mirror.apply(snapshot.state(rt))
    return mirror


@pytest.mark.wallclock
def test_a_receive_that_fails_on_a_bus_read_from_the_loop_is_a_state_not_a_traceback(
    flaky: None,
) -> None:
    """SocketCAN taken down under a running supervisor: the pump reads it on the loop
    (add_reader); the failing receive becomes BUS-OFF once, and the reader rests between
    tries instead of spinning the loop with tracebacks."""
    config = parse_config(
        "buses:\n  robot: {interface: fdflaky, channel: fd}\nunits:\n  - {name: base}\n", "e.yaml"
    )
    notices = BusNotices("robot")
    unhandled: list[dict[str, Any]] = []

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        loop.set_exception_handler(lambda _, context: unhandled.append(context))
        async with Runtime(config) as rt:
            rt.supervisor.subscribe(notices)
            (bus,) = [b for b in FlakyBus.instances if isinstance(b, FdBus)]
            bus.go_down()
            await notices.next()
            assert rt.supervisor.bus_health["robot"].state is BusState.BUS_OFF
            reads = bus.reads
            await asyncio.sleep(1.2)  # real time is what a spinning reader would burn
            assert 1 <= bus.reads - reads <= 4  # one try per RETRY_S, not one per loop turn
            bus.go_up()

    asyncio.run(scenario())
    assert notices.seen == ["bus robot: BUS-OFF: network down: bus-off, or the interface is down"]
    assert unhandled == []


@pytest.mark.wallclock
def test_a_hung_up_bus_resting_after_a_failed_receive_does_not_spin_the_loop(
    flaky: None,
) -> None:
    """A descriptor left hung up (an slcan adapter unplugged, its tty gone): while the
    pump rests after the failed receive, with the watch off, the loop does not step it
    on every turn (epoll reports a hang-up whatever the watched events)."""
    config = parse_config(
        "buses:\n  robot: {interface: fdflaky, channel: fd}\nunits:\n  - {name: base}\n", "e.yaml"
    )
    notices = BusNotices("robot")

    async def scenario() -> int:
        async with Runtime(config) as rt:
            rt.supervisor.subscribe(notices)
            (bus,) = [b for b in FlakyBus.instances if isinstance(b, FdBus)]
            bus.go_down()
            bus._w.close()  # the other end gone: a hang-up on the bus's descriptor
            await notices.next()  # the receive failed: the pump rests, the watch off
            pump, steps = rt.pumps["robot"], 0
            original = pump._step_unguarded

            def counted(fed: bool = False) -> None:
                nonlocal steps
                steps += 1
                original(fed)

            pump._step_unguarded = counted  # type: ignore[method-assign]
            for _ in range(200):  # loop turns, far less than RETRY_S
                await asyncio.sleep(0)
            return steps

    assert asyncio.run(scenario()) <= 3  # the unit's own schedule, not one per turn
