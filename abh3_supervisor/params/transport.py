"""The J1939 transport with RTS/CTS (never BAM), sans-I/O, in both roles (§1.3).

:class:`Sender` sends one message: RTS → CTS → DTs (window by window) → EndOfMsgAck.
:class:`Receiver` takes one: RTS → CTS (at most 16 DTs per CTS, as the maker's Linux
sample asks) → DTs checked in sequence → EndOfMsgAck. Both are fed frames and the time and
return the frames to send; a timeout, an abort or a broken sequence ends them with a
:class:`TransportError` and, where J1939 wants one, an Abort frame to the peer. Every
control frame carries the maker's signature ``00 EF 00`` in bytes 5–7.
"""

from __future__ import annotations

import math
from enum import Enum, IntEnum

from abh3_supervisor.errors import Abh3Error

RTS, CTS, EOMA, ABORT = 0x10, 0x11, 0x13, 0xFF
SIGNATURE = b"\x00\xef\x00"  # the maker's bytes 5–7 (PGN 0xEF00, DP0's): on every TP.CM
DT_BYTES = 7
MAX_PACKETS = 255  # a J1939 message is at most 255 DTs (1785 bytes)
MAX_PER_CTS = 16  # what the maker's Linux sample asks for per CTS
TIMEOUT = 1.25  # s: the Linux sample's wait (the Windows samples wait 1.0 s)
OutFrame = tuple[int, bytes]


class AbortReason(IntEnum):
    BUSY = 1  # already in a session (an RTS while one is open): the maker's samples
    RESOURCES = 2
    TIMEOUT = 3
    CTS_WHILE_SENDING = 4  # 4–8 are J1939-21's; the maker's sources only name 1–3
    UNEXPECTED_DT = 6
    BAD_SEQUENCE = 7


def _reason(code: int) -> str:
    try:
        return AbortReason(code).name.lower().replace("_", " ")
    except ValueError:
        return f"reason {code}"


class TransportError(Abh3Error):
    """A transport session failed: what happened, in words an operator can act on."""

    def __init__(self, message: str, reason: AbortReason | int | None = None) -> None:
        super().__init__(message)
        self.reason = reason


def rts(length: int, max_per_cts: int = 0xFF) -> bytes:
    npk = math.ceil(length / DT_BYTES)
    return bytes([RTS, length & 0xFF, length >> 8, npk, max_per_cts]) + SIGNATURE


def cts(count: int, next_seq: int) -> bytes:
    return bytes([CTS, count, next_seq, 0xFF, 0xFF]) + SIGNATURE


def end_of_msg_ack(length: int) -> bytes:
    npk = math.ceil(length / DT_BYTES)
    return bytes([EOMA, length & 0xFF, length >> 8, npk, 0xFF]) + SIGNATURE


def abort(reason: int) -> bytes:
    return bytes([ABORT, reason, 0xFF, 0xFF, 0xFF]) + SIGNATURE


def dt_frames(message: bytes) -> list[bytes]:
    """Sequence numbers from 1; unused bytes of the last frame are 0xFF (§1.3)."""
    return [
        bytes([i // DT_BYTES + 1]) + message[i : i + DT_BYTES].ljust(DT_BYTES, b"\xff")
        for i in range(0, len(message), DT_BYTES)
    ]


class State(Enum):
    START = "start"  # the sender's RTS is due / the receiver waits for an RTS
    WAIT = "wait"  # for the peer's CTS, DT or EndOfMsgAck
    SENDING = "sending"  # DTs of a window due
    CTS_DUE = "cts due"
    EOMA_DUE = "eoma due"
    DONE = "done"
    FAILED = "failed"


class _Machine:
    def __init__(self, cm_id: int, dt_id: int, timeout: float) -> None:
        self.cm_id, self.dt_id, self.timeout = cm_id, dt_id, timeout
        self.state = State.START
        self.deadline = math.inf
        self.error: TransportError | None = None
        self._out: list[OutFrame] = []

    @property
    def finished(self) -> bool:
        return self.state in (State.DONE, State.FAILED)

    def _fail(self, message: str, reason: AbortReason | int | None, send_abort: bool) -> None:
        if send_abort and reason is not None:
            self._out.append((self.cm_id, abort(reason)))
        self.state, self.deadline = State.FAILED, math.inf
        self.error = TransportError(message, reason)

    def _take(self) -> list[OutFrame]:
        out, self._out = self._out, []
        return out


class Sender(_Machine):
    """Sends ``message`` to the peer; see the module docstring."""

    def __init__(
        self,
        message: bytes,
        cm_id: int,
        dt_id: int,
        now: float,
        *,
        dt_gap: float = 0.0,
        timeout: float = TIMEOUT,
        peer: str = "the drive",
    ) -> None:
        super().__init__(cm_id, dt_id, timeout)
        if not 9 <= len(message) <= MAX_PACKETS * DT_BYTES:
            raise ValueError(f"a J1939 TP message is 9-1785 bytes, not {len(message)}")
        self.length = len(message)
        self.packets = dt_frames(message)
        self.dt_gap, self.peer = dt_gap, peer
        self.deadline = now  # the RTS goes at once
        self.next = 0  # index of the next DT to send
        self.window_end = 0

    def poll(self, now: float) -> list[OutFrame]:
        if self.state is State.START:
            self._out.append((self.cm_id, rts(self.length)))
            self.state, self.deadline = State.WAIT, now + self.timeout
        elif self.state is State.SENDING:
            while now >= self.deadline and self.state is State.SENDING:
                self._out.append((self.dt_id, self.packets[self.next]))
                self.next += 1
                if self.next == self.window_end:  # wait for the next CTS or the ack
                    self.state, self.deadline = State.WAIT, now + self.timeout
                elif self.dt_gap:
                    self.deadline = now + self.dt_gap
        elif self.state is State.WAIT and now >= self.deadline:
            what = "EndOfMsgAck" if self.next == len(self.packets) else "CTS"
            self._fail(
                f"no {what} from {self.peer} within {self.timeout:g} s",
                AbortReason.TIMEOUT,
                True,
            )
        return self._take()

    def on_cm(self, data: bytes, now: float) -> None:
        if self.finished or len(data) < 3:
            return
        kind = data[0]
        if kind == ABORT:
            self._fail(f"{self.peer} aborted the transfer: {_reason(data[1])}", data[1], False)
        elif kind == CTS and self.state is State.WAIT and self.next < len(self.packets):
            count, first = data[1], data[2]
            if count == 0:  # hold: the receiver wants a pause; it owes a CTS in time
                self.deadline = now + self.timeout
            elif self.window_end == 0 and first != 1:
                # the first CTS of a session asks for packet 1 (J1939-21): one asking for
                # another answers an older RTS (the rest of a session we aborted) — not
                # ours to act on or abort; ours still comes, or the timeout does
                return
            elif not 1 <= first <= len(self.packets):
                self._fail(f"{self.peer} asked for DT {first} of {len(self.packets)}", 7, True)
            else:
                self.next = first - 1
                self.window_end = min(len(self.packets), self.next + count)
                self.state, self.deadline = State.SENDING, now
        elif kind == CTS and self.state is State.SENDING:
            self._fail(f"{self.peer} sent a CTS while DTs were going", 4, True)
        elif kind == EOMA and self.state is State.WAIT and self.next == len(self.packets):
            self.state, self.deadline = State.DONE, math.inf

    def next_deadline(self) -> float:
        return self.deadline


class Receiver(_Machine):
    """Takes one message from the peer. ``wait_until``: fail if no RTS comes by then."""

    def __init__(
        self,
        cm_id: int,
        dt_id: int,
        *,
        wait_until: float = math.inf,
        timeout: float = TIMEOUT,
        max_per_cts: int = MAX_PER_CTS,
        peer: str = "the drive",
    ) -> None:
        super().__init__(cm_id, dt_id, timeout)
        self.deadline = wait_until
        self.max_per_cts, self.peer = max_per_cts, peer
        self.length = self.npk = self.received = self.window_end = 0
        self.sender_max = 0xFF
        self._data = bytearray()

    @property
    def message(self) -> bytes:
        return bytes(self._data[: self.length])

    def on_rts(self, data: bytes, now: float) -> bool:
        """An RTS: taken if none was yet (True); the caller aborts one that comes later."""
        if self.state is not State.START or len(data) < 5:
            return False
        self.length = data[1] | data[2] << 8
        self.npk, self.sender_max = data[3], data[4] or 0xFF
        if self.npk != math.ceil(self.length / DT_BYTES) or self.npk == 0:
            self._fail(f"{self.peer} announced {self.length} bytes in {self.npk} DTs", 2, True)
        else:
            self.state, self.deadline = State.CTS_DUE, now
        return True

    def on_cm(self, data: bytes, now: float) -> None:
        if data[:1] == bytes([ABORT]) and not self.finished and self.state is not State.START:
            self._fail(f"{self.peer} aborted the transfer: {_reason(data[1])}", data[1], False)

    def on_dt(self, data: bytes, now: float) -> None:
        if self.state is not State.WAIT or not data:
            return  # a DT outside a window: J1939 ignores it
        if data[0] != self.received + 1:
            self._fail(
                f"{self.peer} sent DT {data[0]}, expected {self.received + 1}",
                AbortReason.BAD_SEQUENCE,
                True,
            )
            return
        self._data += data[1 : 1 + DT_BYTES]
        self.received += 1
        self.deadline = now + self.timeout
        if self.received == self.npk:
            self.state, self.deadline = State.EOMA_DUE, now
        elif self.received == self.window_end:
            self.state, self.deadline = State.CTS_DUE, now

    def poll(self, now: float) -> list[OutFrame]:
        if self.state is State.CTS_DUE:
            count = min(self.max_per_cts, self.sender_max, self.npk - self.received)
            self._out.append((self.cm_id, cts(count, self.received + 1)))
            self.window_end = self.received + count
            self.state, self.deadline = State.WAIT, now + self.timeout
        elif self.state is State.EOMA_DUE:
            self._out.append((self.cm_id, end_of_msg_ack(self.length)))
            self.state, self.deadline = State.DONE, math.inf
        elif now >= self.deadline and self.state is State.START:
            self._fail(f"no reply from {self.peer} within {self.timeout:g} s", None, False)
        elif now >= self.deadline and self.state is State.WAIT:
            self._fail(
                f"{self.peer} stopped sending: DT {self.received + 1} of {self.npk} did not come "
                f"within {self.timeout:g} s",
                AbortReason.TIMEOUT,
                True,
            )
        return self._take()

    def next_deadline(self) -> float:
        return self.deadline
