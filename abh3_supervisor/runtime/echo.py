"""A bus that never hands us our own frames back.

On python-can's ``udp_multicast`` every member of the group receives each datagram, its
sender too, and nothing turns that off. Our machines must not see their own frames: the
supervisor would take its own DP0 commands for another host's, a recording would hold
each sent frame twice.

:class:`MulticastEchoFilter` (``udp_multicast``) sends on a socket of its own whose copies
the kernel drops before they reach us (:mod:`.kernel_echo`: Linux, IPv4). Where that cannot
be had it knows its copies by their bytes: python-can packs each frame with its send
timestamp, so the datagram that comes back is byte for byte the one sent, and another
host's frame never is. A copy is dropped before python-can unpacks it — and, as the
loopback usually delivers it within the sending system call, taken back right after the
send, so the event loop is not woken for it.

:class:`EchoFilter` (any other bus that hears itself: ``receive_own_messages``) remembers
what it sent and drops the first received copy of each by identifier and data. A frame
another host sent that equals one of ours is dropped in its place, once; the copy of ours
that then arrives has nothing left to match and goes through — so a second host sending
exactly our frames is still seen, one frame late.

Both forget entries whose copy never came (a full socket buffer) after ``EXPIRY_S``.
"""

from __future__ import annotations

import contextlib
import logging
import select
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus
from can.interfaces.udp_multicast.bus import SO_TIMESTAMPNS
from can.interfaces.udp_multicast.utils import pack_message, unpack_message

from abh3_supervisor.runtime.kernel_echo import detach, own_sender

log = logging.getLogger(__name__)

EXPIRY_S = 1.0
MAX_PENDING = 4096  # sent frames awaiting their copy: a bound, whatever happens
_TAKE_BACK = socket.MSG_PEEK | socket.MSG_DONTWAIT


class _Wrapper(can.BusABC):
    """Another bus, as this one: what is not received or sent goes straight to it."""

    def __init__(self, bus: can.BusABC, clock: Callable[[], float]) -> None:
        self.inner = bus
        self._clock = clock
        self._lock = threading.Lock()  # a reader thread may receive while the loop sends
        self.echoes_dropped = 0
        super().__init__(channel=bus.channel_info)
        self.channel_info = bus.channel_info
        self._can_protocol = bus.protocol

    def fileno(self) -> int:
        return self.inner.fileno()

    @property
    def state(self) -> can.BusState:
        return self.inner.state

    @state.setter
    def state(self, new: can.BusState) -> None:
        self.inner.state = new

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


class EchoFilter(_Wrapper):
    def __init__(self, bus: can.BusABC, *, clock: Callable[[], float] = time.monotonic) -> None:
        self._pending: deque[tuple[float, int, bytes]] = deque(maxlen=MAX_PENDING)
        super().__init__(bus, clock)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        entry = (self._clock(), msg.arbitration_id, bytes(msg.data))
        with self._lock:  # before sending: the copy may come back before send returns
            self._pending.append(entry)
        try:
            self.inner.send(msg, timeout)
        except BaseException:
            with self._lock:
                self._forget(entry)
            raise

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        while msg is not None and self._is_echo(msg):
            msg = self.inner.recv(0)  # what waits behind it: a copy never ends a read
        if msg is None:
            return None, False  # recv() goes on waiting for the rest of its timeout
        return msg, True  # the inner bus applied its filters

    def _is_echo(self, msg: can.Message) -> bool:
        data, now = bytes(msg.data), self._clock()
        with self._lock:
            pending = self._pending
            while pending and pending[0][0] < now - EXPIRY_S:
                pending.popleft()
            for entry in pending:
                if entry[1] == msg.arbitration_id and entry[2] == data:
                    self._forget(entry)
                    self.echoes_dropped += 1
                    return True
        return False

    def _forget(self, entry: tuple[float, int, bytes]) -> None:
        with contextlib.suppress(ValueError):
            self._pending.remove(entry)

    def set_filters(self, filters: Any = None) -> None:
        self.inner.set_filters(filters)


class MulticastEchoFilter(_Wrapper):
    """python-can's ``udp_multicast`` bus, read and written a datagram at a time (its
    ``GeneralPurposeUdpMulticastBus``: ``send``, ``recv``, the socket), so that our own
    datagrams never reach us or are known by their bytes; see the module docstring.
    ``in_kernel=False``: by their bytes only."""

    def __init__(
        self,
        bus: UdpMulticastBus,
        *,
        clock: Callable[[], float] = time.monotonic,
        in_kernel: bool = True,
    ) -> None:
        self._udp = bus._multicast
        self._socket: socket.socket = self._udp._socket
        # (sent at, datagram), oldest first: copies come back in the order they were sent
        self._pending: deque[tuple[float, bytes]] = deque(maxlen=MAX_PENDING)
        # the socket whose datagrams the kernel keeps from ours (made once the bus is:
        # nothing to leak if it is not), and its send timeout
        self.sender: socket.socket | None = None
        self._sender_timeout: float | None = None
        super().__init__(bus, clock)
        if in_kernel:
            self.sender = own_sender(self._udp)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_fd and self._can_protocol is not can.CanProtocol.CAN_FD:
            raise can.CanOperationError("cannot send FD message over bus with CAN FD disabled")
        datagram = pack_message(msg)  # python-can's own packing: the same bytes on the wire
        if self.sender is not None and self._send_own(self.sender, datagram, timeout):
            return  # no copy comes back: nothing to remember
        entry = (self._clock(), datagram)
        with self._lock:  # before sending: the copy may come back before send returns
            self._pending.append(entry)
        try:
            self._udp.send(datagram, timeout)
        except BaseException:
            with self._lock:
                self._forget(entry)
            raise
        if not timeout:  # a socket with a timeout would wait in recv, whatever the flags
            self._take_back(datagram)

    def _send_own(self, sender: socket.socket, datagram: bytes, timeout: float | None) -> bool:
        """python-can's ``send`` (its timeout and errors) on our own socket; False if that
        socket can no longer send (its address is gone: it is bound to the one it had),
        which is then given up for python-can's own."""
        try:
            if timeout != self._sender_timeout:
                sender.settimeout(timeout)
                self._sender_timeout = timeout
            if sender.send(datagram) < len(datagram):
                raise TimeoutError
        except TimeoutError:
            raise can.CanTimeoutError() from None
        except BlockingIOError as error:  # a full buffer: python-can's error, as its own send
            raise can.CanOperationError("failed to send via socket") from error
        except OSError as error:
            log.warning(
                "udp_multicast: our own sending socket failed (%s); python-can's sends now,"
                " and our copies are known by their bytes",
                error,
            )
            self._give_up_sender()
            return False
        return True

    def _give_up_sender(self) -> None:
        """From now on python-can's socket sends, and our copies are matched by bytes."""
        with self._lock:
            sender, self.sender = self.sender, None
            with contextlib.suppress(OSError):
                detach(self._socket)
            if sender is not None:
                sender.close()

    def shutdown(self) -> None:
        self._give_up_sender()
        super().shutdown()

    def _take_back(self, datagram: bytes) -> None:
        """Drop our copy now if it is already the next datagram waiting (the loopback
        delivers within the send): the loop then does not wake for it. Anything else
        waiting stays where it is."""
        with self._lock:
            try:  # one byte more: a longer datagram cannot look equal
                waiting = self._socket.recv(len(datagram) + 1, _TAKE_BACK)
            except OSError:  # nothing waiting yet: recv drops it when it comes
                return
            if waiting != datagram:
                return
            self._socket.recv(1, socket.MSG_DONTWAIT)  # the rest of a datagram is discarded
            self._is_own(datagram)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if timeout != 0:  # wait outside the lock: a send must not wait for a receive
            readable, _, _ = select.select([self._socket], [], [], timeout)
            if not readable:
                return None, False
        with self._lock:  # the copy may have been taken back since
            while True:  # past our copies to what waits behind them: a copy never ends a
                got = self._datagram()  # read (the pump's, at timeout 0, would stop there)
                if got is None:
                    return None, False  # recv() goes on waiting for the rest of its timeout
                datagram, stamp = got
                if not self._is_own(datagram):
                    break
        try:
            msg = unpack_message(datagram, replace={"timestamp": stamp}, check=True)
        except Exception as exc:  # as python-can's own bus says it
            raise can.CanOperationError("could not unpack received message") from exc
        if msg.is_fd and self._can_protocol is not can.CanProtocol.CAN_FD:
            return None, False
        return msg, False  # filters, if any, are this bus's own (BusABC applies them)

    def _datagram(self) -> tuple[bytes, float] | None:
        """The next datagram waiting and its kernel timestamp, or None. python-can's own
        ``recv(0)`` asks ``select`` first, a system call per datagram and one more to find
        none; with SO_TIMESTAMPNS (Linux) and no send timeout set on the socket (which
        would make any receive wait) it is read at once, checked as python-can checks it."""
        udp = self._udp
        if not udp.timestamp_nanosecond or self._socket.gettimeout():
            got = udp.recv(0)
            return None if got is None else (got[0], got[2])
        try:
            datagram, ancillary, _, _ = self._socket.recvmsg(
                udp.max_buffer, udp.received_ancillary_buffer_size, socket.MSG_DONTWAIT
            )
        except BlockingIOError:  # any other OSError goes up as python-can's recv lets it
            return None
        if len(ancillary) != 1 or ancillary[0][:2] != (socket.SOL_SOCKET, SO_TIMESTAMPNS):
            raise can.CanOperationError("received control message type that was not requested")
        seconds, nanoseconds = struct.unpack(udp.received_timestamp_struct, ancillary[0][2])
        if nanoseconds >= 1_000_000_000:
            raise can.CanOperationError(
                f"Timestamp nanoseconds field was out of range: {nanoseconds}"
            )
        return datagram, seconds + nanoseconds * 1.0e-9

    def _is_own(self, datagram: bytes) -> bool:
        """Whether ``datagram`` is a copy of one we sent (then forgotten); under the lock."""
        pending = self._pending
        if not pending:  # nothing sent lately, or nothing comes back (our own socket)
            return False
        now = self._clock()
        while pending and pending[0][0] < now - EXPIRY_S:
            pending.popleft()
        if pending and pending[0][1] == datagram:  # the usual case: the oldest one
            pending.popleft()
        else:
            for entry in pending:
                if entry[1] == datagram:
                    self._forget(entry)
                    break
            else:
                return False
        self.echoes_dropped += 1
        return True

    def _forget(self, entry: tuple[float, bytes]) -> None:
        with contextlib.suppress(ValueError):
            self._pending.remove(entry)


def without_own_frames(bus: can.BusABC) -> can.BusABC:
    """``bus`` (which hears its own frames), wrapped so that it does not."""
    if isinstance(bus, UdpMulticastBus) and hasattr(bus, "_multicast"):
        return MulticastEchoFilter(bus)
    return EchoFilter(bus)
