"""``interface: wacousb`` — the maker's USB-CAN adapter (RP2040, USB CDC) for python-can.

The adapter has no commands at all: the bitrate is its DIP switches', it never reports bus
state or errors, and it takes the next frame from the host only once the previous one went
out on the bus — with no node acknowledging, output stalls, so every write has a timeout.
It works only while DTR is set. It does not check its received frames for us: we verify
every CRC and count and drop the bad ones. When the device vanishes (unplugged, reset) the
bus keeps running: receiving returns nothing, sending raises ``CanOperationError``, and the
port is reopened as soon as it is back, without the caller doing anything.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
from collections import deque
from typing import Any

import can
import serial

from abh3_supervisor.wacousb import framing

log = logging.getLogger(__name__)
DIP_SWITCHES = {
    250_000: "SW1 off, SW2 off",
    500_000: "SW1 on, SW2 off",
    1_000_000: "SW1 off, SW2 on",
}
DEFAULT_WRITE_TIMEOUT = 0.1  # s; `timeout=None` must not hang on a stalled adapter
REOPEN_INTERVAL = 0.5  # s between attempts to reopen a vanished device
READ_CHUNK = 4096


class WacoUsbBus(can.BusABC):
    """python-can bus for the adapter on ``channel`` (e.g. ``/dev/ttyACM0``).

    ``bitrate`` is only compared with nothing: it cannot be read from the adapter, so a
    warning names the DIP-switch setting it needs. ``write_timeout`` bounds ``send(msg)``
    without a timeout; ``reopen_interval`` paces reopening a vanished device.
    """

    def __init__(
        self,
        channel: Any = None,
        bitrate: int | None = None,
        write_timeout: float = DEFAULT_WRITE_TIMEOUT,
        reopen_interval: float = REOPEN_INTERVAL,
        can_filters: can.typechecking.CanFilters | None = None,
        **kwargs: Any,
    ) -> None:
        if not channel:
            raise can.CanInitializationError(
                "wacousb: give the serial port as channel, e.g. /dev/ttyACM0"
            )
        self.channel = str(channel)
        self.channel_info = f"Waco Giken USB-CAN on {self.channel}"
        self.write_timeout = write_timeout
        self.reopen_interval = reopen_interval
        self._parser = framing.Parser()
        self._received: deque[framing.Frame] = deque()
        self._tail = b""  # the rest of a frame a timed-out write had begun: sent first
        self._lock = threading.Lock()  # the port is replaced on one thread, used on two
        self._serial: serial.Serial | None = None
        self._next_reopen = 0.0
        self.reopens = 0
        self.vanished = 0
        try:
            self._serial = self._open()
        except (serial.SerialException, OSError) as exc:
            raise can.CanInitializationError(
                f"wacousb: cannot open {self.channel}: {_reason(exc)} (is the adapter plugged "
                "in? `ls /dev/ttyACM*`; may you use it? the `dialout` group)"
            ) from exc
        if bitrate is not None:
            switches = DIP_SWITCHES.get(int(bitrate), "not a rate the adapter has")
            log.warning(
                "wacousb %s: the bitrate cannot be checked (the adapter's DIP switches set it, "
                "nothing reads them): make sure they say %d bit/s (%s)",
                self.channel,
                bitrate,
                switches,
            )
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    # ------------------------------------------------------------ counters

    @property
    def crc_errors(self) -> int:
        """Received frames dropped for a wrong CRC."""
        return self._parser.crc_errors

    @property
    def framing_errors(self) -> int:
        """Received byte runs dropped for bad framing (bad hex, length, a lost ETX)."""
        return self._parser.framing_errors

    @property
    def connected(self) -> bool:
        return self._serial is not None

    # ------------------------------------------------------------ the port

    def _open(self) -> serial.Serial:
        port = serial.Serial()
        port.port = self.channel
        port.baudrate = 115200  # ignored by CDC; what the maker's DLL sets
        port.dtr = True  # the firmware only works while DTR is set
        port.rts = True
        port.exclusive = True  # a second program on the same adapter garbles both
        port.open()
        self._tail = b""
        self._parser = _carry_counts(self._parser)
        return port

    def _vanish(self, exc: BaseException) -> None:
        with self._lock:
            port, self._serial = self._serial, None
        if port is None:
            return
        self.vanished += 1
        self._next_reopen = time.monotonic() + self.reopen_interval
        log.warning(
            "wacousb %s: the adapter went away (%s): reopening when it is back",
            self.channel,
            _reason(exc),
        )
        with contextlib.suppress(serial.SerialException, OSError):
            port.close()

    def _reopen(self) -> bool:
        now = time.monotonic()
        if now < self._next_reopen:
            return False
        self._next_reopen = now + self.reopen_interval
        try:
            port = self._open()
        except (serial.SerialException, OSError):
            return False
        with self._lock:
            self._serial = port
        self.reopens += 1
        log.warning("wacousb %s: the adapter is back", self.channel)
        return True

    # ------------------------------------------------------------ receiving

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._received:
                return self._message(self._received.popleft()), False
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            port = self._serial
            if port is None and not self._reopen():
                # never raise here: python-can's reader thread would end with it
                wait = self.reopen_interval if left is None else min(left, self.reopen_interval)
                if wait > 0:
                    time.sleep(wait)  # the pace of reopening, not a synchronisation
                if deadline is not None and time.monotonic() >= deadline:
                    return None, False
                continue
            if port is None:
                port = self._serial
            assert port is not None
            try:
                ready, _, _ = select.select([port.fileno()], [], [], left)
                if not ready:
                    return None, False
                chunk = os.read(port.fileno(), READ_CHUNK)
                if not chunk:  # readable yet empty: the device is gone
                    raise OSError("end of file")
            except (OSError, ValueError, TypeError, serial.SerialException) as exc:
                self._vanish(exc)
                continue
            self._received.extend(self._parser.feed(chunk))
            if not self._received and deadline is not None and time.monotonic() >= deadline:
                return None, False

    def _message(self, frame: framing.Frame) -> can.Message:
        return can.Message(
            timestamp=time.time(),  # the adapter sends none
            arbitration_id=frame.arbitration_id,
            is_extended_id=frame.extended,
            data=frame.data,
            channel=self.channel,
        )

    # ------------------------------------------------------------ sending

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_remote_frame or msg.is_fd or msg.is_error_frame:
            raise can.CanOperationError(
                "wacousb: the adapter sends data frames only (no remote, FD or error frames)"
            )
        frame = framing.encode(msg.arbitration_id, bytes(msg.data), msg.is_extended_id)
        limit = self.write_timeout if timeout is None else timeout
        with self._lock:
            port = self._serial
            if port is None:
                raise can.CanOperationError(f"wacousb {self.channel}: the adapter is not connected")
            try:
                self._write(port.fileno(), frame, time.monotonic() + limit)
                return
            except OSError as exc:
                failure = exc
        self._vanish(failure)  # outside the lock: it takes it
        raise can.CanOperationError(
            f"wacousb {self.channel}: write failed, the adapter went away: {_reason(failure)}"
        ) from failure

    def _write(self, fd: int, frame: bytes, deadline: float) -> None:
        """Write the unfinished tail, then ``frame``, until ``deadline``. A frame is all or
        nothing for the caller: begun, its rest is kept and goes first next time (the stream
        stays well formed); not begun, ``CanOperationError`` says the adapter is stalled."""
        pending = self._tail + frame
        while pending:
            with contextlib.suppress(BlockingIOError):
                pending = pending[os.write(fd, pending) :]
            if not pending:
                break
            left = deadline - time.monotonic()
            if left <= 0:
                break
            select.select([], [fd], [], left)
        if len(pending) > len(frame):  # not even the old tail went out: drop the new frame
            self._tail = pending[: len(pending) - len(frame)]
            raise can.CanOperationError(
                f"wacousb {self.channel}: transmit stalled: the adapter takes no frames "
                "(does any node acknowledge? check wiring, termination and the DIP-switch bitrate)"
            )
        if len(pending) == len(frame):
            self._tail = b""
            raise can.CanOperationError(
                f"wacousb {self.channel}: transmit buffer full: frame not sent"
            )
        self._tail = pending

    def flush_tx_buffer(self) -> None:
        self._tail = b""

    def fileno(self) -> int:
        # the descriptor changes when the device is reopened: python-can must use a reader
        # thread (which calls recv with a timeout), not the event loop's add_reader
        raise NotImplementedError("wacousb reopens its port: no stable file descriptor")

    def shutdown(self) -> None:
        super().shutdown()
        with self._lock:
            port, self._serial = self._serial, None
        self._next_reopen = float("inf")
        if port is not None:
            port.close()


def _carry_counts(old: framing.Parser) -> framing.Parser:
    """A fresh parser after reopening (half a frame from before is garbage), same counts."""
    new = framing.Parser()
    new.crc_errors, new.framing_errors, new.last_error = (
        old.crc_errors,
        old.framing_errors,
        old.last_error,
    )
    return new


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
