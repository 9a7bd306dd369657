"""The host's parameter channel to one unit, sans-I/O: TelABH3 over the J1939 transport.

One exchange at a time per unit (the drive holds one session: §1.3): our request goes out
(:class:`Sender`), then the drive's reply comes in (:class:`Receiver`). Requests queue;
each ends in a :class:`Result` handed to its callback from inside ``poll``/``on_frame``.
After a failed exchange the next one waits :data:`ABORT_GUARD` (a late CTS must not
answer it: :meth:`ParamChannel.poll`).
The per-bus scheduler owns one channel per unit and sends its frames after the DP0
commands, so parameter traffic never delays a keepalive.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from abh3_supervisor.errors import CodecError
from abh3_supervisor.params.telabh3 import DEFAULT_FORMAT, Reply, Request, TelFormat, decode_reply
from abh3_supervisor.params.transport import (
    RTS,
    TIMEOUT,
    AbortReason,
    OutFrame,
    Receiver,
    Sender,
    State,
    abort,
)
from abh3_supervisor.protocol.ids import PF_TP_CM, PF_TP_DT, CanId

NOW = 0.0  # a deadline already past: work is waiting (finite, so a pump arms its timer)
HOST_DT_GAP = 0.001  # s between our DTs: a request is 2–3 DTs, never a burst on the bus
# After a failed exchange, the next RTS waits this long and the drive's transport frames
# are dropped meanwhile (see ParamChannel.poll): J1939-21's Tr, the 200 ms a node may take
# to answer, and 50 ms for frames queued on our side (an adapter, the kernel, the loop).
ABORT_GUARD = 0.25


def tp_ids(destination: int, source: int, priority: int = 0) -> tuple[int, int]:
    """(TP.CM, TP.DT) identifiers from ``source`` to ``destination`` (§1.3)."""
    return (
        CanId(priority, PF_TP_CM, destination, source).to_int(),
        CanId(priority, PF_TP_DT, destination, source).to_int(),
    )


@dataclass(frozen=True, slots=True)
class Result:
    request: Request
    t: float
    reply: Reply | None = None
    error: str | None = None  # transport or codec failure, for the operator

    @property
    def ok(self) -> bool:
        return self.reply is not None and self.reply.ok


Done = Callable[[Result], None]


class Exchange:
    """One request and its reply."""

    def __init__(
        self,
        request: Request,
        fmt: TelFormat,
        ids: tuple[int, int],
        now: float,
        *,
        timeout: float = TIMEOUT,
        dt_gap: float = HOST_DT_GAP,
    ) -> None:
        self.request, self.ids, self.timeout = request, ids, timeout
        self.sender = Sender(request.encode(fmt), *ids, now, dt_gap=dt_gap, timeout=timeout)
        self.receiver: Receiver | None = None
        self.reply: Reply | None = None
        self.error: str | None = None
        self._out: list[OutFrame] = []

    @property
    def finished(self) -> bool:
        return self.reply is not None or self.error is not None

    def on_frame(self, is_dt: bool, data: bytes, now: float) -> None:
        if self.finished:
            return
        if is_dt:
            if self.receiver is not None:
                self.receiver.on_dt(data, now)
        elif data[0] == RTS:  # routed frames are never empty
            if self.receiver is None or not self.receiver.on_rts(data, now):
                # one session each way at a time (§1.3): an RTS while one is open
                self._out.append((self.ids[0], abort(AbortReason.BUSY)))
                self.error = "the drive started a reply before our request was acknowledged"
        elif self.receiver is not None:
            self.receiver.on_cm(data, now)
        else:
            self.sender.on_cm(data, now)
            if self.sender.state is State.DONE:  # acked: its reply must start in time
                self.receiver = Receiver(
                    *self.ids, wait_until=now + self.timeout, timeout=self.timeout
                )
        self._settle()

    def poll(self, now: float) -> list[OutFrame]:
        if not self.finished:
            machine = self.receiver if self.receiver is not None else self.sender
            self._out += machine.poll(now)
            self._settle()
        out, self._out = self._out, []
        return out

    def _settle(self) -> None:
        for machine in (self.sender, self.receiver):
            if machine is not None and machine.error is not None and self.error is None:
                self.error = str(machine.error)
                self._out += machine._take()  # its abort, if any
        if self.receiver is not None and self.receiver.state is State.DONE and not self.finished:
            try:
                self.reply = decode_reply(self.receiver.message)
            except CodecError as exc:
                self.error = f"unreadable reply: {exc}"

    def next_deadline(self) -> float:
        if self._out or self.finished:  # frames to send, or a result to hand over
            return NOW  # finite: the pump arms a timer for it
        machine = self.receiver if self.receiver is not None else self.sender
        return machine.next_deadline()

    def fail(self, why: str) -> None:
        """Give up from outside (a caller's deadline, the bus): the drive is told with an
        abort, so its side of the session closes too and the next request is not busy."""
        if not self.finished:
            self.error = why
            self._out.append((self.ids[0], abort(AbortReason.TIMEOUT)))


class ParamChannel:
    """A unit's queue of TelABH3 requests over the transport; see the module docstring."""

    def __init__(
        self, abh3_id: int, host_id: int, priority: int = 0, fmt: TelFormat = DEFAULT_FORMAT
    ) -> None:
        self.fmt = fmt
        self.ids = tp_ids(abh3_id, host_id, priority)
        self.peer_ids = tp_ids(host_id, abh3_id)  # the drive's, priority bits clear
        self.queue: deque[tuple[Request, Done]] = deque()
        self.current: tuple[Exchange, Done] | None = None
        self.timeout = TIMEOUT
        self.quiet_until = -math.inf  # no RTS before this: a failed exchange's guard
        self.on_work: Callable[[], None] = lambda: None  # its owner polls it from now on

    @property
    def busy(self) -> bool:
        return self.current is not None or bool(self.queue)

    def submit(self, request: Request, done: Done) -> None:
        self.queue.append((request, done))
        self.on_work()

    def cancel(self, why: str) -> None:
        """Fail whatever is queued (the unit is gone, the run ends)."""
        pending = list(self.queue)
        self.queue.clear()
        if self.current is not None:
            exchange, _ = self.current
            exchange.fail(why)
        for request, done in pending:
            done(Result(request, math.nan, error=why))

    def withdraw(self, done: Done, why: str) -> None:
        """One caller stopped waiting: its request leaves the queue, or fails if open;
        the others' requests go on."""
        for entry in self.queue:
            if entry[1] == done:  # the same callback (a bound method is a new object)
                self.queue.remove(entry)
                return
        if self.current is not None and self.current[1] == done:
            self.current[0].fail(why)

    def on_frame(self, is_dt: bool, data: bytes, now: float) -> None:
        if self.current is None:
            # nothing open: ignored, not aborted — another tool on the bus with our host
            # address (a `abh3 param` beside a running service) may own that session, or
            # it is a late frame of an exchange that failed (the guard in poll)
            return
        self.current[0].on_frame(is_dt, data, now)
        self._finish(now)

    def poll(self, now: float) -> list[OutFrame]:
        """The open exchange's frames; the next exchange starts when it ends.

        Not at once after a failure. J1939-21: a CTS answers the most recent RTS of its
        connection, and nothing in it says which RTS — the next request's first CTS asks
        for packet 1 just like the one we gave up on. When we abort (a timeout, a caller
        giving up, the bus refusing a frame), the drive may have put its CTS to the old RTS
        on the wire before it heard the abort; taken by the next request's sender, that CTS
        would clear DTs the drive never asked for (it ignores them, or answers the real RTS
        mid-transfer). So after a failed exchange no RTS goes for ABORT_GUARD, and every
        transport frame from the drive meanwhile finds no exchange open and is dropped; a
        drive answers within J1939's Tr (200 ms), and our abort went after our RTS, so its
        CTS to that RTS is on the wire within Tr of our abort. Sender.on_cm also ignores a
        first CTS that does not ask for packet 1 (the rest of an older session)."""
        out: list[OutFrame] = []
        if self.current is None and self.queue and now >= self.quiet_until:
            request, done = self.queue.popleft()
            self.current = (Exchange(request, self.fmt, self.ids, now, timeout=self.timeout), done)
        if self.current is not None:
            out = out + self.current[0].poll(now)
            self._finish(now)
            if self.current is None and self.queue:  # the next one starts at once
                out += self.poll(now)
        return out

    def _finish(self, now: float) -> None:
        if self.current is None or not self.current[0].finished:
            return
        exchange, done = self.current
        if exchange._out:  # its last frames (an EndOfMsgAck, an abort) go first
            return
        self.current = None
        if exchange.error is not None:  # the drive may still answer it: see poll
            self.quiet_until = now + ABORT_GUARD
        done(Result(exchange.request, now, exchange.reply, exchange.error))

    def on_send_failed(self) -> None:
        if self.current is not None:
            self.current[0].fail("the bus refused a transport frame (is the bus up?)")

    def next_deadline(self) -> float:
        if self.current is None:
            return max(NOW, self.quiet_until) if self.queue else math.inf
        return self.current[0].next_deadline()
