"""The simulated drive's TelABH3 side: parameters, monitors and identity over J1939 TP.

Requests come in any of the accepted forms (§1.3 leaves the form open) and are answered
in the same one; ``accepts`` limits them (a request in another form is ignored, as a
string the drive cannot read: the host gets no reply). Parameters start from the table's
defaults, which the drive overrides with its own set-up (simulator/drive.py); a write of
0x4117 (command-zero timeout), 0x4118 (CAN error timeout) or 0x4119 (wait between the
drive's DTs) changes what the drive does. Unknown addresses get a NAK. Scripted faults:
``tp_lost_cts`` (an RTS is never answered), ``tp_abort`` (the drive aborts, reason 2
resources), ``tp_slow_dt`` (its DTs come ``delay_ms`` apart).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

from abh3_supervisor.config.model import FaultKind
from abh3_supervisor.errors import CodecError
from abh3_supervisor.params import table
from abh3_supervisor.params.session import NOW, tp_ids
from abh3_supervisor.params.telabh3 import (
    Command,
    Reply,
    Request,
    TelFormat,
    decode_request,
    encode_reply,
    wire_form,
)
from abh3_supervisor.params.transport import (
    RTS,
    AbortReason,
    OutFrame,
    Receiver,
    Sender,
    abort,
)

IDENTITY = {0x0: "ABH3", 0x2: "2.3.0.1", 0x4: "SIMULATED", 0x5: "0", 0x8: "AGV", 0xC: "0"}
COMMAND_ZERO, ERROR_TIMEOUT, DT_WAIT = 0x4117, 0x4118, 0x4119


class DriveState(Protocol):
    """What the responder reads of the simulated drive for monitors."""

    def monitor(self, address: int) -> float | None: ...
    def set_command_zero_ms(self, ms: int) -> None: ...
    def set_error_timeout_ms(self, ms: int) -> None: ...


def ms_of(word: int) -> int:
    """A timeout parameter's word in whole ms; 0 (off) for anything not positive."""
    ms = table.to_value(word, "pf")
    return int(ms) if math.isfinite(ms) and ms > 0 else 0


class TelResponder:
    def __init__(
        self,
        abh3_id: int,
        drive: DriveState,
        fault: Callable[[FaultKind, float], float | None],
        accepts: tuple[TelFormat, ...] | None = None,
    ) -> None:
        self.abh3_id, self.drive, self.fault = abh3_id, drive, fault
        # the string forms this drive reads; None: every one
        self.accepts = None if accepts is None else {wire_form(f) for f in accepts}
        self.params = {e.address: table.to_word(e.default, e.kind) for e in table.PARAMETERS}
        self.host = -1
        self.receiver: Receiver | None = None
        self.sender: Sender | None = None
        self._out: list[OutFrame] = []
        self.requests: list[Request] = []  # every request understood, for tests

    @property
    def busy(self) -> bool:
        """In a session: one that ended (an abort, a timeout) no longer counts."""
        return any(m is not None and not m.finished for m in (self.receiver, self.sender))

    def on_frame(self, host: int, is_dt: bool, data: bytes, now: float) -> None:
        if is_dt:
            if self.receiver is not None and host == self.host:
                self.receiver.on_dt(data, now)
            return
        if data[0] == RTS:  # routed frames are never empty
            self._on_rts(host, data, now)
        elif host == self.host and self.sender is not None:
            self.sender.on_cm(data, now)
        elif host == self.host and self.receiver is not None:
            self.receiver.on_cm(data, now)

    def _on_rts(self, host: int, data: bytes, now: float) -> None:
        cm, dt = tp_ids(host, self.abh3_id)
        if self.fault(FaultKind.TP_LOST_CTS, now) is not None:
            return  # heard, never answered
        if self.fault(FaultKind.TP_ABORT, now) is not None:
            self._out.append((cm, abort(AbortReason.RESOURCES)))
            return
        if self.busy:
            self._out.append((cm, abort(AbortReason.BUSY)))
            return
        self.host = host
        self.receiver = Receiver(cm, dt, peer="the host")
        self.receiver.on_rts(data, now)

    def poll(self, now: float) -> list[OutFrame]:
        if self.receiver is None and self.sender is None and not self._out:
            return []  # the usual case: no parameter traffic
        if self.receiver is not None:
            self._out += self.receiver.poll(now)
            if self.receiver.finished:
                message = self.receiver.message if self.receiver.error is None else None
                self.receiver = None
                if message is not None:
                    self._answer(message, now)
        if self.sender is not None:
            self._out += self.sender.poll(now)
            if self.sender.finished:
                self.sender = None
        out, self._out = self._out, []
        return out

    def _answer(self, message: bytes, now: float) -> None:
        try:
            request, fmt = decode_request(message)
        except CodecError:
            return  # the drive ignores what it cannot read: the host times out
        if self.accepts is not None and fmt not in self.accepts:
            return  # a form this drive does not read: as above
        self.requests.append(request)
        reply = self._reply(request)
        slow = self.fault(FaultKind.TP_SLOW_DT, now)
        gap = table.to_value(self.params[DT_WAIT], "pf") / 1000 + (slow or 0.0) / 1000
        cm, dt = tp_ids(self.host, self.abh3_id)
        self.sender = Sender(encode_reply(reply, fmt), cm, dt, now, dt_gap=gap, peer="the host")
        self._out += self.sender.poll(now)

    def _reply(self, request: Request) -> Reply:
        address = request.address
        if request.command is Command.IDENTITY:
            text = IDENTITY.get(address)
            return Reply(text is not None, text or "")
        if request.command is Command.MONITOR:
            value = self.drive.monitor(address)
            if value is None:
                return Reply(False, "")
            kind = table.kind_of(address, monitor=True)
            return Reply(True, f"{_word(value, kind):08X}")
        if address not in self.params:
            return Reply(False, "")
        if request.value is None:
            return Reply(True, f"{self.params[address]:08X}")
        self.params[address] = request.value
        if address == COMMAND_ZERO:
            self.drive.set_command_zero_ms(ms_of(request.value))
        elif address == ERROR_TIMEOUT:
            self.drive.set_error_timeout_ms(ms_of(request.value))
        return Reply(True, "")

    def next_deadline(self) -> float:
        if self._out:
            return NOW  # finite: the pump arms a timer for it
        return min(
            self.receiver.next_deadline() if self.receiver is not None else math.inf,
            self.sender.next_deadline() if self.sender is not None else math.inf,
        )


def _word(value: float, kind: table.Kind) -> int:
    """A monitored value as the drive words it: integers cut, floats to 3 decimals."""
    return table.to_word(int(value) if kind == "int" else round(value, 3), kind)
