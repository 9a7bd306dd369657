"""The host's parameter channel to one unit, sans-I/O: TelABH3 over the J1939 transport.

One exchange at a time per unit (the drive holds one session: §1.3): our request goes out
(:class:`Sender`), then the drive's reply comes in (:class:`Receiver`). Requests queue;
each ends in a :class:`Result` handed to its callback from inside ``poll``/``on_frame``.
After a failed exchange the next one waits :data:`ABORT_GUARD` (a late CTS must not
answer it: :meth:`ParamChannel.poll`).
Which string form a drive reads is not settled by any public source (docs/parameters.md):
a channel given no form (a unit without ``telabh3:``) finds it with its first exchange —
the request itself when it is a read, else an identity read — tried in each of
:data:`~abh3_supervisor.params.telabh3.FORMS` until the drive answers (:class:`_Probe`).
The per-bus scheduler owns one channel per unit and sends its frames after the DP0
commands, so parameter traffic never delays a keepalive.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

from abh3_supervisor.errors import CodecError
from abh3_supervisor.params.telabh3 import (
    FORMS,
    Command,
    Reply,
    Request,
    TelFormat,
    decode_reply,
    form_name,
    pin,
)
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
# While the form is being found, a request the drive acknowledged but does not answer
# within this long was taken to be in a form it cannot read, and the next form is tried.
# A drive answers in milliseconds (J1939-21 gives a node 200 ms for a response); shorter
# than the transport's 1.25 s, so all three forms cost at most ~1.7 s with the guards
# between them, within the start-up check's 2 s (core/verify.py).
PROBE_REPLY_WAIT = 0.4
# the harmless read that settles the form when the first request is no read, or a read
# the drive refused (NAK): every drive has a firmware version (BI 2)
IDENTITY_PROBE = Request(Command.IDENTITY, 0x2)


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
    fmt: TelFormat | None = None  # the string form the request went in (None: none went)

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
        reply_wait: float | None = None,
    ) -> None:
        self.request, self.fmt, self.ids, self.timeout = request, fmt, ids, timeout
        self.reply_wait = timeout if reply_wait is None else reply_wait
        self.sender = Sender(request.encode(fmt), *ids, now, dt_gap=dt_gap, timeout=timeout)
        self.receiver: Receiver | None = None
        self.reply: Reply | None = None
        self.error: str | None = None
        self.rts_seen = False  # the drive started a reply
        self.unreadable = False  # ... that we could not read
        self._out: list[OutFrame] = []

    @property
    def unanswered(self) -> bool:
        """Failed although the drive acknowledged the request: no reply came in time, or
        one we could not read. The drive may not read the form it was sent in."""
        if self.unreadable:
            return True
        return self.receiver is not None and not self.rts_seen and self.receiver.error is not None

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
            self.rts_seen |= self.receiver is not None
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
                    *self.ids, wait_until=now + self.reply_wait, timeout=self.timeout
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
                self.unreadable = True

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


@dataclass(frozen=True, slots=True)
class FormFound:
    """What a channel's probe settled: ``fmt`` the form the drive answers (None: it answers
    none), ``tried`` what each form got before, for the operator."""

    fmt: TelFormat | None
    tried: tuple[str, ...]
    t: float

    def text(self) -> str:
        if self.fmt is None:
            return f"the drive answers none of the TelABH3 forms: {', '.join(self.tried)}"
        before = f" (before: {', '.join(self.tried)})" if self.tried else ""
        return f"the drive reads TelABH3 strings as {form_label(self.fmt)}{before}"


def form_label(fmt: TelFormat) -> str:
    return f"{form_name(fmt)}; pin it with `{pin(fmt)}`"


class _Probe:
    """Finding the form with a caller's request (see the module docstring).

    Per form: the request if it is a read (else :data:`IDENTITY_PROBE`). An ACK settles
    the form. A NAK to the caller's read may be the address, not the form: the identity is
    asked in the same form, and an ACK to it settles the form (the caller gets its NAK).
    No answer, an unreadable one or a NAK: the next form. Any other failure (no CTS, an
    abort, a caller giving up) ends the probe: the form is not the drive's problem then.
    """

    def __init__(self, request: Request, done: Done) -> None:
        self.request, self.done = request, done
        self.forms = list(FORMS)
        self.tried: list[str] = []
        self.read = request.value is None  # a read is harmless: it probes itself
        self.asking = request if self.read else IDENTITY_PROBE
        self.nak: Result | None = None  # the caller's read, refused in the current form

    @property
    def form(self) -> TelFormat:
        return self.forms[0]

    def next_form(self, outcome: str) -> bool:
        """Note what the current form got; False when no form is left."""
        self.tried.append(f"{self.asking.text(self.form)} {outcome}")
        self.forms.pop(0)
        self.asking, self.nak = (self.request if self.read else IDENTITY_PROBE), None
        return bool(self.forms)


class ParamChannel:
    """A unit's queue of TelABH3 requests over the transport; see the module docstring.

    ``fmt`` None: the form is found by the first exchange (:class:`_Probe`); then
    :attr:`fmt` holds it, :attr:`found` says how, and :attr:`on_form` is told.
    """

    def __init__(
        self, abh3_id: int, host_id: int, priority: int = 0, fmt: TelFormat | None = None
    ) -> None:
        self.fmt = fmt
        self.pinned = fmt is not None  # set in the YAML: never probed
        self.found: FormFound | None = None  # the last probe's outcome
        self.on_form: Callable[[FormFound], None] = lambda found: None
        self.ids = tp_ids(abh3_id, host_id, priority)
        self.peer_ids = tp_ids(host_id, abh3_id)  # the drive's, priority bits clear
        self.queue: deque[tuple[Request, Done]] = deque()
        self.current: tuple[Exchange, Done] | None = None
        self._probe: _Probe | None = None  # finding the form, between two of its exchanges
        self.timeout = TIMEOUT
        self.quiet_until = -math.inf  # no RTS before this: a failed exchange's guard
        self.on_work: Callable[[], None] = lambda: None  # its owner polls it from now on

    @property
    def busy(self) -> bool:
        return self.current is not None or bool(self.queue) or self._probe is not None

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
        elif self._probe is not None:
            probe, self._probe = self._probe, None
            pending.insert(0, (probe.request, probe.done))
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
        elif self.current is None and self._probe is not None and self._probe.done == done:
            self._probe = None  # between two forms: nothing is open

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
        first CTS that does not ask for packet 1 (the rest of an older session). The same
        guard separates the forms a probe tries."""
        out: list[OutFrame] = []
        if self.current is None and now >= self.quiet_until:
            self._open(now)
        if self.current is not None:
            out = out + self.current[0].poll(now)
            self._finish(now)
            if self.current is None and (self.queue or self._probe) and now >= self.quiet_until:
                out += self.poll(now)  # the next one starts at once
        return out

    def _open(self, now: float) -> None:
        probe = self._probe
        if probe is None and self.queue:
            request, done = self.queue.popleft()
            if self.fmt is not None:
                self.current = (
                    Exchange(request, self.fmt, self.ids, now, timeout=self.timeout),
                    done,
                )
                return
            probe = self._probe = _Probe(request, done)
        if probe is not None:
            exchange = Exchange(
                probe.asking,
                probe.form,
                self.ids,
                now,
                timeout=self.timeout,
                reply_wait=PROBE_REPLY_WAIT,
            )
            self.current = (exchange, probe.done)

    def _finish(self, now: float) -> None:
        if self.current is None or not self.current[0].finished:
            return
        exchange, done = self.current
        if exchange._out:  # its last frames (an EndOfMsgAck, an abort) go first
            return
        self.current = None
        if exchange.error is not None:  # the drive may still answer it: see poll
            self.quiet_until = now + ABORT_GUARD
        result: Result | None = Result(
            exchange.request, now, exchange.reply, exchange.error, exchange.fmt
        )
        if self._probe is not None and result is not None:
            result = self._probing(self._probe, exchange, result, now)
        if result is not None:  # None: the probe goes on (or the caller's write goes next)
            done(result)

    def _probing(
        self, probe: _Probe, exchange: Exchange, result: Result, now: float
    ) -> Result | None:
        """One exchange of a probe ended: the caller's result, or None to go on."""
        reply = exchange.reply
        if reply is not None and reply.ok:
            self._settle(FormFound(probe.form, tuple(probe.tried), now))
            if exchange.request is probe.request:
                return result
            if probe.nak is not None:  # the caller's read was refused in a readable form
                return probe.nak
            self.queue.appendleft((probe.request, probe.done))  # the write, in that form
            return None
        asked_itself = exchange.request is probe.request and probe.request != IDENTITY_PROBE
        if reply is not None and probe.read and asked_itself:
            probe.nak, probe.asking = result, IDENTITY_PROBE  # the address, or the form?
            return None
        if reply is None and not exchange.unanswered:
            self._probe = None  # not the form: the transport, the bus or the caller
            return replace(result, request=probe.request)  # the caller's, not our BI 2
        outcome = "NAK" if reply is not None else f"no reply within {PROBE_REPLY_WAIT:g} s"
        if exchange.unreadable:
            outcome = "an unreadable reply"
        if probe.next_form(outcome):
            return None
        found = FormFound(None, tuple(probe.tried), now)
        self._settle(found)
        hint = "set telabh3: in the unit to the form the drive takes (docs/parameters.md)"
        return Result(probe.request, now, error=f"{found.text()}; {hint}")

    def _settle(self, found: FormFound) -> None:
        self._probe = None
        self.found = found
        if found.fmt is not None:
            self.fmt = found.fmt
        self.on_form(found)

    def on_send_failed(self) -> None:
        if self.current is not None:
            self.current[0].fail("the bus refused a transport frame (is the bus up?)")

    def next_deadline(self) -> float:
        if self.current is None:
            waiting = self.queue or self._probe is not None
            return max(NOW, self.quiet_until) if waiting else math.inf
        return self.current[0].next_deadline()
