"""Taking clients on the control socket at a bounded cost per event-loop turn.

The socket shares its loop with the buses, so nothing a crowd of clients does may hold a
turn for long: at most ``ACCEPT_PER_TURN`` connections are accepted per turn (the rest
wait in the kernel's backlog, where waiting costs the loop nothing), a client past
``max_clients`` is refused before anything is built for it — one line saying why, and
its socket kept only to read what it sends until it hangs up (closing with its request
unread would reset the connection and lose the line) — and at most ``REQUESTS_PER_TURN``
requests of all clients together are answered per turn (:class:`Turns`). What repeats is
logged once per ``Tally.interval`` with a count, never once per connection.
"""

from __future__ import annotations

import asyncio
import collections
import errno
import logging
import socket
from collections.abc import Callable

log = logging.getLogger(__name__)
BACKLOG = 256  # connections the kernel holds while the loop takes ACCEPT_PER_TURN a turn
ACCEPT_PER_TURN = 8
REQUESTS_PER_TURN = 8
LINGER_S = 2.0  # a refused client has this long to read its refusal and hang up
MAX_LINGERING = 64  # refused sockets kept open at once; past that, closed at once
RETRY_S = 0.1  # out of file descriptors: accept again after this (the socket stays ready)


class Tally:
    """An event that can repeat thousands of times a second, logged at most once per
    ``interval``: the first at once, the rest as a count when the interval ends."""

    def __init__(self, level: int, text: str, interval: float = 10.0) -> None:
        self.level, self.text, self.interval = level, text, interval
        self.count = 0
        self._quiet_until = -1e300
        self._flush: asyncio.TimerHandle | None = None

    def note(self, loop: asyncio.AbstractEventLoop) -> None:
        now = loop.time()
        if now >= self._quiet_until:
            log.log(self.level, "%s", self.text)
            self._quiet_until = now + self.interval
            return
        self.count += 1
        if self._flush is None:
            self._flush = loop.call_at(self._quiet_until, self._report)

    def _report(self) -> None:
        self._flush = None
        if self.count:
            log.log(self.level, "%s (%d more in %g s)", self.text, self.count, self.interval)
            self.count = 0

    def close(self) -> None:
        if self._flush is not None:
            self._flush.cancel()
            self._report()


class Acceptor:
    """Accepts on a listening socket for as long as it is open: ``admit`` takes each
    client while ``full()`` is false; the others are sent ``refusal`` and let go."""

    def __init__(
        self,
        sock: socket.socket,
        admit: Callable[[socket.socket], None],
        full: Callable[[], bool],
        refusal: bytes,
        refused: Tally,
    ) -> None:
        self.sock, self.admit, self.full, self.refusal = sock, admit, full, refusal
        self.refused = refused
        self.loop = asyncio.get_running_loop()
        self._lingering: dict[socket.socket, asyncio.TimerHandle] = {}
        self._out_of_files = Tally(logging.ERROR, "control socket: out of file descriptors")

    def start(self) -> None:
        self.sock.setblocking(False)
        self.sock.listen(BACKLOG)
        self.loop.add_reader(self.sock.fileno(), self._ready)

    def close(self) -> None:
        if self.sock.fileno() >= 0:
            self.loop.remove_reader(self.sock.fileno())
            self.sock.close()
        for conn in list(self._lingering):
            self._drop(conn)
        self.refused.close()
        self._out_of_files.close()

    def _ready(self) -> None:
        for _ in range(ACCEPT_PER_TURN):
            try:
                conn, _ = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM):
                    # the socket stays readable: pause, or the loop would spin on it
                    self._out_of_files.note(self.loop)
                    self.loop.remove_reader(self.sock.fileno())
                    self.loop.call_later(RETRY_S, self._resume)
                return
            conn.setblocking(False)
            if self.full():
                self._refuse(conn)
            else:
                self.admit(conn)

    def _resume(self) -> None:
        if self.sock.fileno() >= 0:
            self.loop.add_reader(self.sock.fileno(), self._ready)

    def _refuse(self, conn: socket.socket) -> None:
        self.refused.note(self.loop)
        try:
            conn.send(self.refusal)  # a few dozen bytes into an empty buffer: never blocks
            conn.shutdown(socket.SHUT_WR)
        except OSError:
            conn.close()
            return
        if len(self._lingering) >= MAX_LINGERING:
            self._discard_input(conn)
            conn.close()
            return
        self._lingering[conn] = self.loop.call_later(LINGER_S, self._drop, conn)
        self.loop.add_reader(conn.fileno(), self._drain, conn)

    def _drain(self, conn: socket.socket) -> None:
        if not self._discard_input(conn):
            self._drop(conn)  # it hung up (or broke): done

    @staticmethod
    def _discard_input(conn: socket.socket) -> bool:
        """Read what the refused client sent; False once it hung up."""
        try:
            return bool(conn.recv(4096))
        except (BlockingIOError, InterruptedError):
            return True
        except OSError:
            return False

    def _drop(self, conn: socket.socket) -> None:
        handle = self._lingering.pop(conn, None)
        if handle is not None:
            handle.cancel()
        if conn.fileno() >= 0:
            self.loop.remove_reader(conn.fileno())
            conn.close()


class Turns:
    """At most ``per_turn`` requests of all clients together begin per event-loop turn;
    the others wait for a later turn, so a client's pipelined flood of requests (or a
    crowd's) is spread out, and the bus timer is served between them."""

    def __init__(self, per_turn: int = REQUESTS_PER_TURN) -> None:
        self.per_turn = per_turn
        self._used = 0
        self._waiting: collections.deque[asyncio.Future[None]] = collections.deque()
        self._reset_due = False

    async def enter(self) -> None:
        if self._used < self.per_turn and not self._waiting:
            self._used += 1
            self._reset_soon()
            return
        waiter = asyncio.get_running_loop().create_future()
        self._waiting.append(waiter)
        self._reset_soon()
        await waiter  # a cancelled waiter is skipped when its turn comes

    def _reset_soon(self) -> None:
        if not self._reset_due:
            self._reset_due = True
            asyncio.get_running_loop().call_soon(self._reset)

    def _reset(self) -> None:
        """The next turn: its share of the waiting requests go."""
        self._reset_due = False
        self._used = 0
        while self._waiting and self._used < self.per_turn:
            waiter = self._waiting.popleft()
            if not waiter.done():
                waiter.set_result(None)
                self._used += 1
        if self._used:
            self._reset_soon()
