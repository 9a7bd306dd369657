"""The simulator's udp_multicast bus without our own frames (simulator/multicast.py): sent
on a socket whose copies the kernel keeps from the bus's socket (a BPF filter on its
source address and port), or, where that cannot be had, known by their bytes; read and
written as python-can packs and checks them.

A multicast group's datagrams leave the machine; these tests need none. The bus here is a
UDP socket on 127.0.0.1 that the group's address points back at — the way the group hands
a sender its own datagrams — reached only through ``fileno()``, as python-can's own; and
another socket plays the other host."""

from __future__ import annotations

import select
import socket
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import can
import msgpack  # type: ignore[import-untyped]
import pytest
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from abh3_supervisor.runtime.echo import without_own_frames
from abh3_supervisor.simulator import multicast
from abh3_supervisor.simulator.multicast import EXPIRY_S, MulticastBus, own_sender

pytestmark = pytest.mark.wallclock  # real sockets

ID = 0x0CEF0102
GROUP = "127.0.0.1"  # the loopback: what is sent to it comes back to the bus's socket


class LoopbackBus(can.BusABC):
    """A bus whose socket receives what is sent to 127.0.0.1 on its port (python-can's
    ``udp_multicast`` as our code sees it: its descriptor)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(channel=GROUP, **kwargs)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, multicast.SO_TIMESTAMPNS, 1)
        self.sock.bind((GROUP, 0))
        self._can_protocol = can.CanProtocol.CAN_20

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise AssertionError("our code sends on a socket of its own")

    def shutdown(self) -> None:
        super().shutdown()
        self.sock.close()


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Bus:
    ours: MulticastBus
    other: socket.socket  # another host: sends datagrams to ours
    clock: Clock

    def from_other(self, msg: can.Message) -> None:
        self.other.sendto(pack_message(msg), self.ours.sock.getsockname())

    def waiting(self) -> bool:
        return bool(select.select([self.ours.sock], [], [], 0)[0])

    def wait(self) -> None:
        select.select([self.ours.sock], [], [], 1.0)


def _bus(**kwargs: Any) -> Iterator[Bus]:
    clock = Clock()
    ours = MulticastBus(LoopbackBus(**kwargs), GROUP, clock=clock)
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield Bus(ours, other, clock)
    ours.shutdown()
    other.close()


@pytest.fixture
def kernel_bus() -> Iterator[Bus]:
    """Our copies kept from us by the kernel."""
    yield from _bus()


@pytest.fixture
def bus(monkeypatch: pytest.MonkeyPatch) -> Iterator[Bus]:
    """Our copies known by their bytes (the kernel refuses the filter)."""

    def refused(sock: socket.socket, program: bytes) -> None:
        raise PermissionError("no filters here")

    monkeypatch.setattr(multicast, "attach", refused)
    yield from _bus()


def frame(data: bytes, t: float = 1000.0) -> can.Message:
    return can.Message(arbitration_id=ID, data=data, is_extended_id=True, timestamp=t)


def test_the_factory_picks_it_for_udp_multicast() -> None:
    bus = without_own_frames(LoopbackBus(), "udp_multicast", GROUP)
    try:
        assert isinstance(bus, MulticastBus) and bus.in_kernel
    finally:
        bus.shutdown()


# --- in the kernel ----------------------------------------------------------------------


def test_in_the_kernel_our_copy_never_reaches_our_socket(kernel_bus: Bus) -> None:
    ours = kernel_bus.ours
    ours.send(frame(b"\x01" * 8), timeout=0)
    assert not kernel_bus.waiting() and ours.recv(0.05) is None
    assert ours.echoes_dropped == 0 and not ours.pending  # nothing was remembered


def test_in_the_kernel_another_hosts_frame_equal_to_ours_still_comes(kernel_bus: Bus) -> None:
    msg = frame(b"\x00" * 8, t=1000.0)
    kernel_bus.ours.send(msg, timeout=0)
    kernel_bus.from_other(msg)  # byte for byte our datagram, from another socket
    got = kernel_bus.ours.recv(1.0)
    assert got is not None and bytes(got.data) == b"\x00" * 8
    assert kernel_bus.ours.recv(0) is None


def test_what_goes_out_is_python_cans_own_datagram(kernel_bus: Bus) -> None:
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    sender = kernel_bus.ours.sender
    source = sender.getsockname()
    sender.connect(listener.getsockname())  # the same source, another destination
    msg = frame(b"\x07" * 8)
    msg.channel = "b"
    try:
        kernel_bus.ours.send(msg, timeout=0)
        data, came_from = listener.recvfrom(4096)
        assert data == pack_message(msg) and came_from == source
    finally:
        listener.close()


def test_the_sender_has_the_bus_s_destination_and_ttl(kernel_bus: Bus) -> None:
    sender, receiving = kernel_bus.ours.sender, kernel_bus.ours.sock
    assert sender.getpeername() == (GROUP, receiving.getsockname()[1])
    ttl = sender.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
    assert ttl == receiving.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)


def test_a_frame_is_read_as_python_can_reads_it(kernel_bus: Bus) -> None:
    """The data python-can would unpack, stamped with the kernel's receive time."""
    sent = frame(bytes(range(8)), t=5.0)
    before = time.time()
    kernel_bus.from_other(sent)
    kernel_bus.wait()
    got = kernel_bus.ours.recv(0)
    assert got is not None and kernel_bus.ours.recv(0) is None
    expected = unpack_message(pack_message(sent), replace={"timestamp": got.timestamp})
    assert got.equals(expected) and got.is_rx
    assert before - 0.001 <= got.timestamp <= time.time()


def test_receiving_nothing_asks_no_select(kernel_bus: Bus, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(select, "select", None)  # not asked: it would fail
    assert kernel_bus.ours.recv(0) is None


def test_blocking_receive_waits_for_the_next_frame(kernel_bus: Bus) -> None:
    assert kernel_bus.ours.recv(0.02) is None
    kernel_bus.from_other(frame(b"\x09" * 8))
    got = kernel_bus.ours.recv(1.0)
    assert got is not None and bytes(got.data) == b"\x09" * 8


def test_a_datagram_that_is_not_a_frame_is_python_cans_error(kernel_bus: Bus) -> None:
    kernel_bus.other.sendto(b"\xc1 not msgpack", kernel_bus.ours.sock.getsockname())
    kernel_bus.wait()
    with pytest.raises(can.CanOperationError, match="could not unpack"):
        kernel_bus.ours.recv(0)


def test_fd_frames_are_refused_on_a_bus_without_fd(kernel_bus: Bus) -> None:
    with pytest.raises(can.CanOperationError, match="CAN FD disabled"):
        kernel_bus.ours.send(can.Message(arbitration_id=ID, is_fd=True, data=bytes(12)))
    fd = can.Message(arbitration_id=ID, is_fd=True, data=bytes(12), timestamp=1.0)
    kernel_bus.from_other(fd)
    kernel_bus.from_other(frame(b"\x04" * 8))  # behind it: the read goes on
    kernel_bus.wait()
    got = kernel_bus.ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x04" * 8


def test_the_bus_s_filters_apply() -> None:
    filters = [{"can_id": ID, "can_mask": 0x1FFFFFFF, "extended": True}]
    for bus in _bus(can_filters=filters):
        other = frame(b"\x01" * 8)
        other.arbitration_id = ID + 1
        bus.from_other(other)
        bus.from_other(frame(b"\x02" * 8))  # behind a refused frame: the read goes on
        bus.wait()
        got = bus.ours.recv(0)
        assert got is not None and bytes(got.data) == b"\x02" * 8


def test_a_sender_that_fails_is_made_again(kernel_bus: Bus) -> None:
    """An address gone under the connected socket: that send fails (the pump counts it),
    and the next goes out on a new socket, its copies still kept from us."""
    ours = kernel_bus.ours
    ours.sender.close()  # any send on it now fails
    with pytest.raises(can.CanOperationError, match="failed to send via socket"):
        ours.send(frame(b"\x06" * 8), timeout=0)
    ours.send(frame(b"\x07" * 8), timeout=0)
    assert ours.in_kernel and ours.recv(0.05) is None


# --- by their bytes ---------------------------------------------------------------------


def test_a_copy_comes_back_and_is_dropped_when_read(bus: Bus) -> None:
    assert not bus.ours.in_kernel
    bus.ours.send(frame(b"\x01" * 8), timeout=0)
    bus.wait()
    assert bus.ours.recv(0) is None and bus.ours.echoes_dropped == 1 and not bus.ours.pending


def test_a_copy_behind_another_hosts_frame_is_dropped_when_read(bus: Bus) -> None:
    bus.from_other(frame(b"\x02" * 8, t=5.0))  # waiting before our copy comes back
    bus.ours.send(frame(b"\x03" * 8), timeout=0)
    bus.wait()
    got = bus.ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x02" * 8 and got.timestamp != 5.0
    assert bus.ours.recv(0) is None  # our copy, dropped
    assert bus.ours.echoes_dropped == 1 and not bus.waiting()


def test_our_copies_never_end_a_read_of_what_waits_behind_them(bus: Bus) -> None:
    """The pump reads with ``recv(0)`` until it gets None: copies of ours first in the
    queue must not stop it before another host's frame behind them."""
    for n in (1, 2):
        bus.ours.send(frame(bytes([n]) * 8, t=1000.0 + n), timeout=0)
    bus.from_other(frame(b"\x09" * 8, t=5.0))
    bus.wait()
    time.sleep(0.01)  # all three queued
    got = bus.ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x09" * 8
    assert bus.ours.echoes_dropped == 2 and bus.ours.recv(0) is None


def test_another_hosts_frame_equal_to_ours_shows_at_once(bus: Bus) -> None:
    bus.ours.send(frame(b"\x00" * 8, t=1000.0), timeout=0)
    bus.from_other(frame(b"\x00" * 8, t=1000.5))  # same id and data, its own send time
    got = bus.ours.recv(1.0)
    assert got is not None and got.arbitration_id == ID and bytes(got.data) == b"\x00" * 8
    assert bus.ours.echoes_dropped == 1


def test_a_copy_that_never_came_is_forgotten(bus: Bus) -> None:
    bus.ours.sender.connect(("127.0.0.1", 9))  # the discard port: the copy is lost
    msg = frame(b"\x05" * 8)
    bus.ours.send(msg, timeout=0)
    assert len(bus.ours.pending) == 1
    bus.clock.t += EXPIRY_S + 0.1
    bus.from_other(msg)  # the very same bytes, from elsewhere, after the expiry
    assert bus.ours.recv(1.0) is not None  # no longer mistaken for our copy
    assert bus.ours.echoes_dropped == 0 and not bus.ours.pending


def test_without_a_source_address_the_copies_are_known_by_their_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where routing gives the group no source address, nothing is fixed to match."""

    class Sourceless(socket.socket):
        def getsockname(self) -> Any:
            return "0.0.0.0", super().getsockname()[1]

    receiving = LoopbackBus()
    monkeypatch.setattr(socket, "socket", Sourceless)
    sender, in_kernel = own_sender(receiving, GROUP)
    monkeypatch.undo()
    sender.close()
    receiving.shutdown()
    assert not in_kernel


def test_what_goes_out_packs_as_python_can_packs() -> None:
    """msgpack's own packer, kept: byte for byte python-can's ``pack_message``."""
    msg = frame(bytes(range(8)), t=1234.5)
    msg.channel = "b"
    for bus in _bus():
        listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        listener.bind(("127.0.0.1", 0))
        bus.ours.sender.connect(listener.getsockname())
        for _ in range(2):  # the packer is used again
            bus.ours.send(msg, timeout=0)
            assert listener.recv(4096) == pack_message(msg)
        listener.close()
        assert msgpack.unpackb(pack_message(msg), raw=False)["data"] == bytes(range(8))


def test_the_filter_drops_our_address_and_port_only() -> None:
    """Same port on another address (another host), another port on our address (another
    program here): both pass; only our own address and port are dropped."""
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    ours = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ours.bind(("127.0.0.1", 0))
    address, port = ours.getsockname()
    elsewhere = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    elsewhere.bind(("127.0.0.2", port))
    here = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    here.bind(("127.0.0.1", 0))
    sockets = [receiver, ours, elsewhere, here]
    try:
        multicast.attach(receiver, multicast.source_filter(address, port))
        for sender, data in ((ours, b"ours"), (elsewhere, b"elsewhere"), (here, b"here")):
            sender.sendto(data, receiver.getsockname())
        receiver.settimeout(1.0)
        got = {receiver.recv(64), receiver.recv(64)}
        receiver.setblocking(False)
        with pytest.raises(BlockingIOError):
            receiver.recv(64)
        assert got == {b"elsewhere", b"here"}
    finally:
        for sock in sockets:
            sock.close()
