"""python-can's ``udp_multicast`` bus (``abh3 simulate``'s) without our own frames.

Every member of the group receives each datagram, its sender too, and the socket has no
option against it; our machines must not see their own frames (the supervisor would take
its own commands for another host's, a recording would hold each sent frame twice).

So the frames go out on a socket of their own (:func:`own_sender`), connected to the
group, so that they carry its address and port as their source, and the bus's socket —
reached through ``bus.fileno()`` — gets a classic BPF socket filter dropping exactly the
datagrams with that source: the kernel drops our copies before they are queued, so they
neither wake the loop nor cost a read. Another host's datagrams have another address,
another program on this machine another port (ours is bound without ``SO_REUSEADDR``);
python-can's members send from the group's port. The destination, TTL (the bus's own),
loopback and bytes are python-can's. Where routing gives no source address of our own
(``0.0.0.0``), off Linux or IPv4, or where the kernel refuses the filter, the copies are
known by their bytes instead: python-can packs each frame with its send timestamp, so a
copy is byte for byte the datagram sent, and another host's frame never is (forgotten
after ``EXPIRY_S`` if it never comes back).

:class:`MulticastBus` reads and writes the datagrams itself, as python-can packs and
checks them (msgpack, ``SO_TIMESTAMPNS``), a frame a call: the step reads ~400 a second.
benchmarks/alone.py's bare python-can host keeps python-can's own receive and drops its
copies the same way (:func:`own_sender`).
"""

from __future__ import annotations

import array
import collections
import os
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import can
import msgpack  # type: ignore[import-untyped]

EXPIRY_S = 1.0  # a copy known by its bytes that has not come back by then never will
SO_TIMESTAMPNS = 35  # Linux's values; the socket module does not name them
SO_ATTACH_FILTER = 26
MAX_DATAGRAM = 4096  # python-can's receive buffer
_STAMP = struct.Struct("@ll")  # struct timespec
_SKF_NET_OFF = -0x100000  # classic BPF: an offset from the network (IP) header
# classic BPF opcodes (linux/filter.h): load a half word / word at k, jump if A == k, return
_LDH_ABS, _LD_ABS, _JEQ, _RET = 0x28, 0x20, 0x15, 0x06


def source_filter(address: str, port: int) -> bytes:
    """A ``struct sock_filter`` program dropping UDP/IPv4 datagrams from ``address:port``
    (a UDP socket's filter sees the UDP header at offset 0, the IP header at
    ``_SKF_NET_OFF``: its source address at 12)."""
    source = struct.unpack("!I", socket.inet_aton(address))[0]
    program = [
        (_LDH_ABS, 0, 0, 0),  # the UDP source port
        (_JEQ, 0, 3, port),  # another port: accept
        (_LD_ABS, 0, 0, (_SKF_NET_OFF + 12) & 0xFFFFFFFF),
        (_JEQ, 0, 1, source),  # another address: accept
        (_RET, 0, 0, 0),  # ours: dropped
        (_RET, 0, 0, 0xFFFFFFFF),
    ]
    return b"".join(struct.pack("HBBI", *instruction) for instruction in program)


def attach(sock: socket.socket, program: bytes) -> None:
    """``program`` as ``sock``'s filter (the kernel copies it: nothing to keep alive)."""
    code = array.array("B", program)
    fprog = struct.pack("HL", len(program) // 8, code.buffer_info()[0])  # struct sock_fprog
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


def own_sender(bus: can.BusABC, group: str) -> tuple[socket.socket, bool]:
    """A socket to send ``bus``'s datagrams on (``group``: its channel), and whether the
    bus's socket never receives them (the kernel drops them); else they come back."""
    with socket.socket(fileno=os.dup(bus.fileno())) as receiving:  # the bus's own socket
        port = receiving.getsockname()[1]
        linux_v4 = sys.platform.startswith("linux") and receiving.family == socket.AF_INET
        sender = socket.socket(receiving.family, socket.SOCK_DGRAM)
        try:
            if receiving.family == socket.AF_INET:
                ttl = receiving.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL)
                sender.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, ttl)
            else:
                hops = receiving.getsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS)
                sender.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hops)
            sender.connect((group, port))
        except OSError as exc:
            sender.close()
            raise can.CanInitializationError(f"cannot send to {group} port {port}: {exc}") from exc
        address, own = sender.getsockname()[:2]
        if not linux_v4 or address == "0.0.0.0":  # nothing of ours to know them by
            return sender, False
        try:
            attach(receiving, source_filter(address, own))
        except OSError:
            return sender, False
        return sender, True


class MulticastBus(can.BusABC):
    """``bus`` (python-can's ``udp_multicast`` on ``group``), never giving back our frames."""

    def __init__(
        self, bus: can.BusABC, group: str, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.inner, self.group, self.clock = bus, group, clock
        self.sock = socket.socket(fileno=os.dup(bus.fileno()))  # the bus's socket, shared
        self.stamped = True
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)  # as python-can asks
        except OSError:
            self.stamped = False
        self.ancillary = socket.CMSG_SPACE(_STAMP.size) if self.stamped else 0
        self.packer = msgpack.Packer(use_bin_type=True)  # python-can's packing
        self.lock = threading.Lock()  # a thread may receive while the loop sends
        # (sent at, datagram) of the copies known by their bytes, oldest first
        self.pending: collections.deque[tuple[float, bytes]] = collections.deque(maxlen=4096)
        self.echoes_dropped = 0
        self.wanted: Any = None  # the bus's filters, if any
        self.fd = bus.protocol is can.CanProtocol.CAN_FD
        self.sender, self.in_kernel = own_sender(bus, group)
        self.sender_timeout: float | None = None
        super().__init__(channel=group, can_filters=bus.filters)
        self.channel_info = bus.channel_info

    @property
    def protocol(self) -> can.CanProtocol:
        return self.inner.protocol

    def set_filters(self, filters: Any = None) -> None:
        self.wanted = filters or None
        super().set_filters(filters)

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_fd and not self.fd:
            raise can.CanOperationError("cannot send FD message over bus with CAN FD disabled")
        datagram = self.packer.pack(
            {
                "timestamp": msg.timestamp,
                "arbitration_id": msg.arbitration_id,
                "is_extended_id": msg.is_extended_id,
                "is_remote_frame": msg.is_remote_frame,
                "is_error_frame": msg.is_error_frame,
                "channel": msg.channel,
                "dlc": msg.dlc,
                "data": msg.data,
                "is_fd": msg.is_fd,
                "bitrate_switch": msg.bitrate_switch,
                "error_state_indicator": msg.error_state_indicator,
            }
        )
        if not self.in_kernel:  # before sending: the copy may come back before send returns
            with self.lock:
                self.pending.append((self.clock(), datagram))
        sender = self.sender
        try:
            if timeout != self.sender_timeout:
                sender.settimeout(timeout)
                self.sender_timeout = timeout
            if sender.send(datagram) < len(datagram):
                raise TimeoutError
        except TimeoutError:
            raise can.CanTimeoutError() from None
        except BlockingIOError as error:  # a full buffer, as python-can says it
            raise can.CanOperationError("failed to send via socket") from error
        except OSError as error:  # our source address went away: connect again
            self.renew()
            raise can.CanOperationError("failed to send via socket") from error

    def renew(self) -> None:
        """A new sending socket (the routing may give it another source address)."""
        with self.lock:
            old = self.sender
            try:
                self.sender, self.in_kernel = own_sender(self.inner, self.group)
            except (OSError, can.CanError):  # no route now either: the next failure tries again
                return
            self.sender_timeout = None
            old.close()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame (not ours, past the filters), as python-can's ``recv``: read at
        once, without asking ``select`` first (which costs a system call per frame)."""
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                datagram, ancillary, _, _ = self.sock.recvmsg(
                    MAX_DATAGRAM, self.ancillary, socket.MSG_DONTWAIT
                )
            except BlockingIOError:
                if timeout == 0 or not self.wait(end):
                    return None
                continue
            if self.pending and self.is_own(datagram):
                continue
            if self.stamped:
                if len(ancillary) != 1 or ancillary[0][:2] != (socket.SOL_SOCKET, SO_TIMESTAMPNS):
                    raise can.CanOperationError("received control message type not requested")
                seconds, nanoseconds = _STAMP.unpack(ancillary[0][2])
                stamp = seconds + nanoseconds * 1.0e-9
            else:
                stamp = time.time()
            try:
                fields = msgpack.unpackb(datagram, raw=False)
                fields["timestamp"] = stamp
                msg = can.Message(check=True, **fields)
            except Exception as exc:  # as python-can's own bus says it
                raise can.CanOperationError("could not unpack received message") from exc
            if (msg.is_fd and not self.fd) or (self.wanted is not None and not self.matches(msg)):
                continue
            return msg

    def wait(self, end: float | None) -> bool:
        """Whether a datagram waits before ``end`` (None: for ever)."""
        left = None if end is None else max(0.0, end - time.monotonic())
        return bool(select.select([self.sock], [], [], left)[0])

    def matches(self, msg: can.Message) -> bool:
        """python-can's filter rule (``BusABC.set_filters``)."""
        return any(
            ("extended" not in f or f["extended"] == msg.is_extended_id)
            and (f["can_id"] ^ msg.arbitration_id) & f["can_mask"] == 0
            for f in self.wanted
        )

    def is_own(self, datagram: bytes) -> bool:
        """Whether ``datagram`` is a copy of one we sent (then forgotten)."""
        with self.lock:
            pending, now = self.pending, self.clock()
            while pending and pending[0][0] < now - EXPIRY_S:
                pending.popleft()
            for entry in pending:
                if entry[1] == datagram:
                    pending.remove(entry)
                    self.echoes_dropped += 1
                    return True
        return False

    def shutdown(self) -> None:
        super().shutdown()
        self.sender.close()
        self.sock.close()
        self.inner.shutdown()
