"""Per-bus state from what the interface reports (sans-I/O): bus-off, error-passive, a
full transmit queue, failing sends — and the way back.

Sources: python-can error frames (SocketCAN's layout, ``linux/can/error.h``: the error
class in the identifier, controller state in data[1], the error counters in data[6:8]) and
the exceptions ``send`` raises (``CanOperationError.error_code`` is the errno: ENOBUFS is a
full transmit queue, ENETDOWN a bus-off or downed interface). Interfaces that report
neither (the maker's adapter, ``virtual``) stay ``ok`` unless sends fail.

Recovery: from bus-off, a full queue or failing sends, once a frame was sent *and* one
received after it (the bus carries traffic again); from warning or error-passive, on the
controller saying so (restarted, active, counters below 96) or after ``QUIET_S`` without an
error frame while frames arrive.
"""

from __future__ import annotations

import errno
from dataclasses import dataclass
from enum import StrEnum

# SocketCAN error classes (identifier bits) and controller states (data[1])
ERR_TX_TIMEOUT = 0x001
ERR_CRTL = 0x004
ERR_ACK = 0x020
ERR_BUSOFF = 0x040
ERR_RESTARTED = 0x100
ERR_CNT = 0x200
CRTL_RX_WARNING, CRTL_TX_WARNING = 0x04, 0x08
CRTL_RX_PASSIVE, CRTL_TX_PASSIVE = 0x10, 0x20
CRTL_ACTIVE = 0x40
WARNING_LIMIT, PASSIVE_LIMIT = 96, 128  # error counter thresholds (ISO 11898-1)
QUIET_S = 5.0


class BusState(StrEnum):
    OK = "ok"
    WARNING = "error-warning"
    PASSIVE = "error-passive"
    BUS_OFF = "bus-off"
    TX_FULL = "tx queue full"
    SEND_FAILING = "sends failing"


@dataclass(frozen=True, slots=True)
class BusStateChange:
    bus: str
    t: float
    old: BusState
    new: BusState
    detail: str


class BusHealth:
    def __init__(self, bus: str) -> None:
        self.bus = bus
        self.state = BusState.OK
        self.since = 0.0
        self.detail = ""
        self.error_frames = 0
        self.changes: list[BusStateChange] = []  # drained by the owner
        self._last_error = -1e300
        self._sent_since_fault = False

    def _set(self, state: BusState, now: float, detail: str) -> None:
        if state is self.state:
            self.detail = detail or self.detail
            return
        self.changes.append(BusStateChange(self.bus, now, self.state, state, detail))
        self.state, self.since, self.detail = state, now, detail
        self._sent_since_fault = False

    def drain(self) -> list[BusStateChange]:
        out, self.changes = self.changes, []
        return out

    # ------------------------------------------------------------ inputs

    def on_error_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        self.error_frames += 1
        self._last_error = now
        cls = arbitration_id
        crtl = data[1] if len(data) > 1 else 0
        if cls & ERR_BUSOFF:
            self._set(BusState.BUS_OFF, now, "the controller went bus-off")
        elif cls & ERR_RESTARTED:
            self._set(BusState.OK, now, "the controller restarted")
        elif cls & ERR_CRTL and crtl & (CRTL_RX_PASSIVE | CRTL_TX_PASSIVE):
            self._set(BusState.PASSIVE, now, _counters("error-passive", data))
        elif cls & ERR_CRTL and crtl & (CRTL_RX_WARNING | CRTL_TX_WARNING):
            if self.state is BusState.OK:
                self._set(BusState.WARNING, now, _counters("error counters ≥ 96", data))
        elif self.state in (BusState.WARNING, BusState.PASSIVE) and (
            (cls & ERR_CRTL and crtl & CRTL_ACTIVE)
            or (cls & ERR_CNT and len(data) >= 8 and max(data[6], data[7]) < WARNING_LIMIT)
        ):
            self._set(BusState.OK, now, _counters("the controller is error-active again", data))

    def on_send_error(self, code: int | None, message: str, now: float) -> None:
        words = message.lower()
        if code == errno.ENOBUFS:
            self._set(BusState.TX_FULL, now, "the transmit queue is full (no node acks?)")
        elif "full" in words or "stalled" in words:  # interfaces without an errno say so
            self._set(BusState.TX_FULL, now, message)
        elif code == errno.ENETDOWN:
            if self.state is not BusState.BUS_OFF:
                self._set(BusState.BUS_OFF, now, "network down: bus-off, or the interface is down")
        elif self.state in (BusState.OK, BusState.WARNING, BusState.PASSIVE):
            self._set(BusState.SEND_FAILING, now, message)

    def on_sent(self, now: float) -> None:
        self._sent_since_fault = True

    def on_received(self, now: float) -> None:
        if self.state in (BusState.BUS_OFF, BusState.TX_FULL, BusState.SEND_FAILING):
            if self._sent_since_fault:
                self._set(BusState.OK, now, "frames go out and come in again")
        elif (
            self.state in (BusState.WARNING, BusState.PASSIVE) and now - self._last_error >= QUIET_S
        ):
            self._set(BusState.OK, now, f"no error frame for {QUIET_S:g} s")


def _counters(what: str, data: bytes) -> str:
    if len(data) >= 8 and (data[6] or data[7]):
        return f"{what} (tx errors {data[6]}, rx errors {data[7]})"
    return what
