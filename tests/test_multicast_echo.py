"""The udp_multicast echo filter (runtime/echo.py): our own datagrams sent on a socket
whose copies the kernel keeps from ours (runtime/kernel_echo.py); or, where that cannot
be had, known by their bytes, dropped before python-can unpacks them, and taken back
right after the send.

A multicast group's datagrams leave the machine; these tests need none. python-can's own
``udp_multicast`` code reads and writes a UDP socket on 127.0.0.1 that sends to itself —
the way the group hands a sender its own datagrams — and another socket plays the other
host. Every byte still goes through python-can's packing, sending and receiving."""

from __future__ import annotations

import select
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import can
import pytest
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.bus import SO_TIMESTAMPNS, GeneralPurposeUdpMulticastBus
from can.interfaces.udp_multicast.utils import pack_message

from abh3_supervisor.runtime import echo, kernel_echo
from abh3_supervisor.runtime.echo import MulticastEchoFilter, without_own_frames

pytestmark = pytest.mark.wallclock  # real sockets

ID = 0x0CEF0102


class _Loopback(GeneralPurposeUdpMulticastBus):
    """python-can's socket handler on a unicast socket that sends to itself."""

    def _create_socket(self, address_family: socket.AddressFamily) -> socket.socket:
        sock = socket.socket(address_family, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.timestamp_nanosecond = True
        sock.bind(("127.0.0.1", 0))
        self.port = sock.getsockname()[1]  # the destination: this socket itself
        return sock


class LoopbackBus(UdpMulticastBus):
    def __init__(self) -> None:
        can.BusABC.__init__(self, "127.0.0.1")
        self._multicast = _Loopback("127.0.0.1", 0, 1)
        self._can_protocol = can.CanProtocol.CAN_20


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Bus:
    ours: MulticastEchoFilter
    other: socket.socket  # another host: sends datagrams to ours
    clock: Clock

    def from_other(self, msg: can.Message) -> None:
        self.other.sendto(pack_message(msg), self.ours._socket.getsockname())

    def waiting(self) -> bool:
        return bool(select.select([self.ours._socket], [], [], 0)[0])


def _bus(in_kernel: bool) -> Iterator[Bus]:
    clock = Clock()
    ours = MulticastEchoFilter(LoopbackBus(), clock=clock, in_kernel=in_kernel)
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield Bus(ours, other, clock)
    ours.shutdown()
    other.close()


@pytest.fixture
def bus() -> Iterator[Bus]:
    """Our copies known by their bytes."""
    yield from _bus(in_kernel=False)


@pytest.fixture
def kernel_bus() -> Iterator[Bus]:
    """Our copies kept from us by the kernel."""
    yield from _bus(in_kernel=True)


def frame(data: bytes, t: float = 1000.0) -> can.Message:
    return can.Message(arbitration_id=ID, data=data, is_extended_id=True, timestamp=t)


def test_the_factory_picks_it_for_python_cans_udp_multicast() -> None:
    bus = without_own_frames(LoopbackBus())
    try:
        assert isinstance(bus, MulticastEchoFilter)
    finally:
        bus.shutdown()


@pytest.mark.parametrize("timeout", [0, None])
def test_our_copy_is_taken_back_during_the_send(bus: Bus, timeout: float | None) -> None:
    bus.ours.send(frame(b"\x01" * 8), timeout=timeout)
    # the loopback delivered it within the send, and it is gone already: nothing wakes
    assert bus.ours.echoes_dropped == 1
    assert not bus.waiting()
    assert bus.ours.recv(0.05) is None


def test_what_goes_out_is_python_cans_own_datagram(bus: Bus) -> None:
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    bus.ours._udp._send_destination = listener.getsockname()
    msg = frame(b"\x07" * 8)
    try:
        bus.ours.send(msg, timeout=0)
        assert listener.recv(4096) == pack_message(msg)  # the wire is unchanged
    finally:
        listener.close()
    assert bus.ours.echoes_dropped == 0 and len(bus.ours._pending) == 1  # not back: waits


def test_a_copy_behind_another_hosts_frame_is_dropped_when_read(bus: Bus) -> None:
    bus.from_other(frame(b"\x02" * 8, t=5.0))  # waiting before our copy comes back
    bus.ours.send(frame(b"\x03" * 8), timeout=0)
    assert bus.ours.echoes_dropped == 0  # the other's frame stays first, untouched
    got = bus.ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x02" * 8 and got.timestamp != 5.0
    assert bus.ours.recv(0) is None  # our copy, dropped before it is unpacked
    assert bus.ours.echoes_dropped == 1 and not bus.waiting()


def test_another_hosts_frame_equal_to_ours_shows_at_once(bus: Bus) -> None:
    bus.ours.send(frame(b"\x00" * 8, t=1000.0), timeout=0)
    bus.from_other(frame(b"\x00" * 8, t=1000.5))  # same id and data, its own send time
    got = bus.ours.recv(1.0)
    assert got is not None and got.arbitration_id == ID and bytes(got.data) == b"\x00" * 8
    assert bus.ours.echoes_dropped == 1


def test_a_copy_that_never_came_is_forgotten(bus: Bus) -> None:
    bus.ours._udp._send_destination = ("127.0.0.1", 9)  # the discard port: the copy is lost
    msg = frame(b"\x05" * 8)
    bus.ours.send(msg, timeout=0)
    assert len(bus.ours._pending) == 1
    bus.clock.t += echo.EXPIRY_S + 0.1
    bus.from_other(msg)  # the very same bytes, from elsewhere, after the expiry
    assert bus.ours.recv(1.0) is not None  # no longer mistaken for our copy
    assert bus.ours.echoes_dropped == 0 and not bus.ours._pending


def test_a_failed_send_leaves_nothing_to_match(bus: Bus) -> None:
    bus.ours._udp._send_destination = ("256.0.0.1", 1)  # no such address: sendto fails
    msg = frame(b"\x06" * 8)
    with pytest.raises(can.CanError):
        bus.ours.send(msg, timeout=0)
    assert not bus.ours._pending


def test_blocking_receive_waits_for_the_next_frame(bus: Bus) -> None:
    assert bus.ours.recv(0.02) is None
    bus.from_other(frame(b"\x09" * 8))
    got = bus.ours.recv(1.0)
    assert got is not None and bytes(got.data) == b"\x09" * 8


def test_our_copies_never_end_a_read_of_what_waits_behind_them(bus: Bus) -> None:
    """The pump reads with ``recv(0)`` until it gets None: a copy of ours first in the
    queue must not stop it before another host's frame behind the copy."""
    bus.ours._udp._send_destination = ("127.0.0.1", 9)  # sent, and its copy not back yet
    sent = [frame(bytes([n]) * 8, t=1000.0 + n) for n in (1, 2)]
    for msg in sent:
        bus.ours.send(msg, timeout=0)
    own = bus.ours._socket.getsockname()
    for msg in sent:  # the copies come back late, with another host's frame after them
        bus.other.sendto(pack_message(msg), own)
    bus.from_other(frame(b"\x09" * 8, t=5.0))
    select.select([bus.ours._socket], [], [], 1.0)
    got = bus.ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x09" * 8
    assert bus.ours.echoes_dropped == 2 and bus.ours.recv(0) is None


def test_a_datagram_is_read_as_python_can_reads_it_without_asking_select(
    bus: Bus, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The data and the kernel's receive time, as python-can's ``recv`` gives them."""
    sent = [frame(bytes([n]) * 8, t=5.0 + n) for n in (1, 2)]
    for msg in sent:
        bus.from_other(msg)
    select.select([bus.ours._socket], [], [], 1.0)
    theirs = bus.ours._udp.recv(0)
    assert theirs is not None
    monkeypatch.setattr(select, "select", None)  # not asked: it would fail
    monkeypatch.setattr(bus.ours._udp, "recv", None)
    ours = bus.ours._datagram()
    assert ours is not None and bus.ours._datagram() is None
    assert [theirs[0], ours[0]] == [pack_message(m) for m in sent]
    assert abs(ours[1] - theirs[2]) < 5.0 and ours[1] >= theirs[2]  # the same wall clock


def test_a_socket_given_a_send_timeout_is_read_by_python_can_never_waiting(bus: Bus) -> None:
    """A send with a timeout leaves it on the socket, which then makes any receive wait
    for as long: such a socket is read python-can's way, after ``select``."""
    bus.ours.send(frame(b"\x01" * 8), timeout=0.5)
    assert bus.ours._socket.gettimeout() == 0.5
    calls: list[float | None] = []
    recv = bus.ours._udp.recv

    def counted(timeout: float | None = None) -> Any:
        calls.append(timeout)
        return recv(timeout)

    bus.ours._udp.recv = counted  # type: ignore[method-assign]
    bus.from_other(frame(b"\x02" * 8))
    select.select([bus.ours._socket], [], [], 1.0)
    got = bus.ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x02" * 8 and bus.ours.recv(0) is None
    assert calls == [0, 0, 0]  # the copy of the timed send, the frame, then none


# --- in the kernel ----------------------------------------------------------------------


def test_in_the_kernel_our_copy_never_reaches_our_socket(kernel_bus: Bus) -> None:
    ours = kernel_bus.ours
    assert ours.sender is not None
    ours.send(frame(b"\x01" * 8), timeout=0)
    assert not kernel_bus.waiting() and ours.recv(0.05) is None
    assert ours.echoes_dropped == 0 and not ours._pending  # nothing was remembered


def test_in_the_kernel_another_hosts_frame_equal_to_ours_still_comes(kernel_bus: Bus) -> None:
    msg = frame(b"\x00" * 8, t=1000.0)
    kernel_bus.ours.send(msg, timeout=0)
    kernel_bus.from_other(msg)  # byte for byte our datagram, from another socket
    got = kernel_bus.ours.recv(1.0)
    assert got is not None and bytes(got.data) == b"\x00" * 8
    assert kernel_bus.ours.recv(0) is None


def test_in_the_kernel_what_goes_out_is_python_cans_own_datagram(kernel_bus: Bus) -> None:
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    sender = kernel_bus.ours.sender
    assert sender is not None
    source = sender.getsockname()
    sender.connect(listener.getsockname())  # the same source, another destination
    msg = frame(b"\x07" * 8)
    try:
        kernel_bus.ours.send(msg, timeout=0)
        data, came_from = listener.recvfrom(4096)
        assert data == pack_message(msg) and came_from == source
    finally:
        listener.close()


def test_in_the_kernel_the_sender_is_python_cans_own_destination_and_ttl(kernel_bus: Bus) -> None:
    udp, sender = kernel_bus.ours._udp, kernel_bus.ours.sender
    assert sender is not None
    assert sender.getpeername() == (udp.group, udp.port)
    ttl = sender.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
    assert ttl == udp._socket.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 1


def test_in_the_kernel_a_sender_that_fails_is_given_up_for_python_cans_socket(
    kernel_bus: Bus,
) -> None:
    """An address gone under the connected socket: the frame still goes out, python-can's
    way, and from then on our copies are known by their bytes; the filter goes too."""
    ours = kernel_bus.ours
    assert ours.sender is not None
    source = ours.sender.getsockname()
    ours.sender.close()  # any send on it now fails
    ours.send(frame(b"\x06" * 8), timeout=0)
    assert ours.sender is None
    assert ours.echoes_dropped == 1 and ours.recv(0.05) is None  # sent, its copy taken back
    successor = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:  # whatever has that address and port now is heard
        successor.bind(source)
        successor.sendto(pack_message(frame(b"\x08" * 8)), ours._socket.getsockname())
        got = ours.recv(1.0)
        assert got is not None and bytes(got.data) == b"\x08" * 8
    finally:
        successor.close()


def test_in_the_kernel_a_failed_send_is_python_cans_error(kernel_bus: Bus) -> None:
    ours = kernel_bus.ours
    assert ours.sender is not None
    ours.sender.close()
    ours._udp._send_destination = ("256.0.0.1", 1)  # python-can's own send fails too
    with pytest.raises(can.CanOperationError, match="failed to send via socket"):
        ours.send(frame(b"\x06" * 8), timeout=0)


def _known_by_their_bytes(ours: MulticastEchoFilter) -> None:
    """``ours`` has no socket of its own: its copy comes back and is taken back."""
    try:
        assert ours.sender is None
        ours.send(frame(b"\x01" * 8), timeout=0)
        assert ours.echoes_dropped == 1 and ours.recv(0.05) is None
    finally:
        ours.shutdown()


def test_without_a_source_address_the_copies_are_known_by_their_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where routing gives the group no source address, nothing is fixed to match."""

    class Sourceless(socket.socket):
        def getsockname(self) -> Any:
            return "0.0.0.0", super().getsockname()[1]

    bus = LoopbackBus()
    monkeypatch.setattr(socket, "socket", Sourceless)
    ours = MulticastEchoFilter(bus)
    monkeypatch.undo()
    _known_by_their_bytes(ours)


def test_where_the_kernel_refuses_the_copies_are_known_by_their_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def refused(sock: socket.socket, program: bytes) -> None:
        raise PermissionError("no filters here")

    monkeypatch.setattr(kernel_echo, "attach", refused)
    ours = MulticastEchoFilter(LoopbackBus())
    _known_by_their_bytes(ours)


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
        kernel_echo.attach(receiver, kernel_echo.source_filter(address, port))
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
