"""One client's socket on the event loop: lines in, bytes out, nothing else.

Not asyncio's transports and streams: each of those leaves a reference cycle behind
(the transport keeps a bound method of itself), so thousands of clients coming and going
left thousands of objects for the cycle collector, whose full pass then held the bus loop
for 10-15 ms. Here a closed connection is freed by reference counting alone. It is also
as small as the control socket needs: reading pauses while ``MAX_PENDING`` lines wait to be
answered (a client pipelining requests waits for its answers, it does not fill our memory),
and writing never blocks — what the socket does not take is queued, and the caller decides
when a queue is too long (the server drops a client that stops reading).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import select
import socket
from collections.abc import Callable

from abh3_supervisor.service.protocol import LineSplitter

READ_CHUNK = 16 * 1024  # what one turn splits: 16 KiB of newlines cost ~1 ms
MAX_PENDING = 256  # lines read and not yet answered: reading pauses beyond this


class Connection:
    def __init__(self, sock: socket.socket) -> None:
        self.sock, self.fd = sock, sock.fileno()
        self.loop = asyncio.get_running_loop()
        self._splitter = LineSplitter()
        self._pending: collections.deque[bytes | None] = collections.deque()
        self._out = bytearray()
        self._waiter: asyncio.Future[None] | None = None
        self._reading = self._ended = self._closed = False
        self._unwritable = False  # its end is gone: what it sent is still read and done
        self.on_hangup: Callable[[], None] | None = None  # the client's end read: it left
        self._resume()

    async def read_line(self) -> bytes | None:
        """The next line (without its newline); ``None`` for one longer than the protocol
        allows, whose rest was dropped. :class:`EOFError` once the client hung up."""
        while not self._pending:
            if self._ended or self._closed:
                raise EOFError
            self._resume()
            self._waiter = self.loop.create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._pending.popleft()

    def write(self, data: bytes) -> None:
        if self._closed or self._unwritable:
            return
        if not self._out:
            try:
                sent = self.sock.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self._cannot_write()
                return
            if sent == len(data):
                return
            data = data[sent:]
            self.loop.add_writer(self.fd, self._writable)
        self._out += data

    @property
    def queued(self) -> int:
        """Bytes written and not yet taken by the socket."""
        return len(self._out)

    def is_closing(self) -> bool:
        return self._closed or self._unwritable

    def hung_up(self) -> bool:
        """The client has gone, or can send nothing more (it shut its sending side): its
        end was read, or the kernel says so while lines it sent before still wait here."""
        if self._ended or self._closed:
            return True
        poller = select.poll()
        poller.register(self.fd, select.POLLRDHUP)  # POLLHUP and POLLERR come unasked
        return bool(poller.poll(0))

    def close(self) -> None:
        """At once: one more try to send what is queued, what the client sent is read and
        dropped (closing with input unread would reset the connection and could lose our
        last line on its side), and the socket is closed. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.on_hangup = None  # it refers to the client: no cycle left to collect
        self._pause()
        if self._out:
            self.loop.remove_writer(self.fd)
            with contextlib.suppress(OSError):  # a client that does not read loses the rest
                self.sock.send(self._out)
            self._out.clear()
        with contextlib.suppress(OSError):
            for _ in range(4):  # what the socket holds; a client still sending may lose
                if not self.sock.recv(READ_CHUNK):
                    break
        self.sock.close()
        self._pending.clear()
        self._wake()

    def _readable(self) -> None:
        try:
            data = self.sock.recv(READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if data:
            self._pending.extend(self._splitter.feed(data))
            if len(self._pending) >= MAX_PENDING:
                self._pause()  # until they are answered (lines() resumes)
        else:
            self._ended = True
            self._pause()
            if self.on_hangup is not None:
                self.on_hangup()  # at once, even while one of its requests is under way
        self._wake()

    def _writable(self) -> None:
        try:
            sent = self.sock.send(self._out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._cannot_write()
            return
        del self._out[:sent]
        if not self._out:
            self.loop.remove_writer(self.fd)

    def _cannot_write(self) -> None:
        """It is gone: nothing more can reach it. The lines it sent before are still read
        and handled in order — an e-stop among them too — until its end."""
        self._unwritable = True
        if self._out:
            self.loop.remove_writer(self.fd)
            self._out.clear()

    def _resume(self) -> None:
        if not self._reading and not self._ended and not self._closed:
            self._reading = True
            self.loop.add_reader(self.fd, self._readable)

    def _pause(self) -> None:
        if self._reading:
            self._reading = False
            self.loop.remove_reader(self.fd)

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)
