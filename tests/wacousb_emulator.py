"""An emulation of the maker's USB-CAN adapter firmware on a pseudo-terminal.

Written from the adapter's description (params-and-usbcan doc §2) without the driver's
code: its own CRC (bit by bit), its own parser, its own encoder. Host side: a symlink
standing for ``/dev/ttyACM0`` to the pty's slave; CAN side: a python-can ``virtual``
bus. Like the firmware it takes the next host frame only once the previous one is on the
bus (``stall()`` stops that, as a bus with no acknowledging node does), drops bad frames
silently, holds at most 64 frames for the host and drops on overflow. ``unplug()`` and
``plug()`` make the device vanish and return under the same path.
"""

from __future__ import annotations

import os
import select
import threading
import tty
from collections import deque
from pathlib import Path

import can

RING = 64
HEX = frozenset(b"0123456789ABCDEF")


def crc_ccitt(text: bytes) -> int:
    """CRC-16, poly 0x1021, MSB first, init 0xFFFF, final XOR 0xFFFF — bit by bit."""
    crc = 0xFFFF
    for byte in text:
        for bit in range(7, -1, -1):
            top = (crc >> 15) ^ (byte >> bit & 1)
            crc = (crc << 1) & 0xFFFF
            if top:
                crc ^= 0x1021
    return crc ^ 0xFFFF


def firmware_frame(msg: can.Message) -> bytes:
    flag = (0x10 if msg.is_extended_id else 0) | msg.dlc
    text = f"{flag:02X}{msg.arbitration_id:08X}{bytes(msg.data).hex().upper()}".encode()
    return b"\x02" + text + f"{crc_ccitt(text):04X}".encode() + b"\x03"


def check_host_frame(body: bytes) -> can.Message:
    """A host frame's text between STX and ETX, checked strictly; ValueError if wrong."""
    if not body or any(b not in HEX for b in body):
        raise ValueError(f"not upper-case hex: {body!r}")
    flag = int(body[:2], 16)
    if flag & ~0x1F:
        raise ValueError(f"FLAG {flag:02X} has bits the firmware does not know")
    dlc = flag & 0x0F
    if dlc > 8 or len(body) != 2 + 8 + 2 * dlc + 4:
        raise ValueError(f"length {len(body)} for FLAG {flag:02X}")
    if int(body[-4:], 16) != crc_ccitt(body[:-4]):
        raise ValueError(f"bad CRC in {body!r}")
    ident = int(body[2:10], 16)
    if ident >> (29 if flag & 0x10 else 11):
        raise ValueError(f"id {ident:X} too wide")
    return can.Message(
        arbitration_id=ident,
        is_extended_id=bool(flag & 0x10),
        data=bytes.fromhex(body[10:-4].decode()),
    )


class AdapterEmulator:
    def __init__(self, link: Path, can_channel: str) -> None:
        self.link = link
        self.can_channel = can_channel
        self.can = can.Bus(interface="virtual", channel=can_channel)
        self.lock = threading.Condition()
        self.host_frames: list[bytes] = []  # every frame the host wrote, STX to ETX
        self.bad: list[str] = []  # why each rejected host frame was wrong
        self.junk = 0  # bytes outside any frame
        self.forwarded = 0  # host frames put on the CAN bus
        self.to_host: deque[bytes] = deque()  # the 64-frame ring
        self.dropped = 0  # CAN frames lost to a full ring
        self.raw_out = bytearray()  # bytes being written to the host (a frame, or injected)
        self._stalled = False
        self._held = False
        self._stop = False
        self._inbuf = bytearray()
        self.master = -1
        self.slave = -1
        self._wake_r, self._wake_w = os.pipe()
        self.plug()
        self._threads = [
            threading.Thread(target=self._serial_side, daemon=True),
            threading.Thread(target=self._can_side, daemon=True),
        ]
        for t in self._threads:
            t.start()

    # ------------------------------------------------------------ test controls

    def plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no signals from ETX (^C) before the host sets raw
        tmp = self.link.with_suffix(".new")
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.link)
        with self.lock:
            self.master, self.slave = master, slave
            self._inbuf.clear()
            self.raw_out.clear()
        self._wake()

    def unplug(self) -> None:
        with self.lock:
            master, slave, self.master, self.slave = self.master, self.slave, -1, -1
            self.to_host.clear()
        self.link.unlink()
        os.close(master)  # the host's reads now fail: the device is gone
        os.close(slave)
        self._wake()

    def stall(self, stalled: bool = True) -> None:
        """No node acknowledges: the firmware takes no more frames from the host."""
        with self.lock:
            self._stalled = stalled
        self._wake()

    def hold_output(self, held: bool = True) -> None:
        """Stop writing to the host (frames pile up in the 64-frame ring)."""
        with self.lock:
            self._held = held
        self._wake()

    def inject(self, raw: bytes) -> None:
        """Raw bytes for the host, ahead of the ring (a corrupted frame, noise)."""
        with self.lock:
            self.raw_out += raw
        self._wake()

    def wait_for(self, predicate: object, timeout: float = 5.0) -> bool:
        with self.lock:
            return self.lock.wait_for(predicate, timeout)  # type: ignore[arg-type]

    def close(self) -> None:
        with self.lock:
            self._stop = True
        self._wake()
        for t in self._threads:
            t.join(2)
        if self.master >= 0:
            os.close(self.master)
            os.close(self.slave)
        os.close(self._wake_r)
        os.close(self._wake_w)
        self.can.shutdown()

    # ------------------------------------------------------------ firmware

    def _wake(self) -> None:
        os.write(self._wake_w, b"x")

    def _can_side(self) -> None:
        while not self._stop:
            msg = self.can.recv(0.02)
            if msg is None:
                continue
            with self.lock:
                if self.master < 0:
                    continue
                if len(self.to_host) >= RING:
                    self.dropped += 1
                else:
                    self.to_host.append(firmware_frame(msg))
                self.lock.notify_all()
            self._wake()

    def _serial_side(self) -> None:
        while True:
            with self.lock:
                if self._stop:
                    return
                master = self.master
                if not self.raw_out and self.to_host and not self._held:
                    self.raw_out += self.to_host.popleft()
                reading = master >= 0 and not self._stalled
                writing = master >= 0 and bool(self.raw_out) and not self._held
            try:
                rl, wl, _ = select.select(
                    [self._wake_r, *([master] if reading else [])],
                    [master] if writing else [],
                    [],
                    1.0,
                )
                if self._wake_r in rl:
                    os.read(self._wake_r, 4096)
                if master in wl:
                    with self.lock:
                        n = os.write(master, self.raw_out)
                        del self.raw_out[:n]
                if master in rl:
                    self._from_host(os.read(master, 4096))
            except OSError:
                continue  # unplugged meanwhile, or the host closed its side for a moment

    def _from_host(self, chunk: bytes) -> None:
        with self.lock:
            self._inbuf += chunk
            while True:
                start = self._inbuf.find(b"\x02")
                if start < 0:
                    self.junk += len(self._inbuf)
                    self._inbuf.clear()
                    break
                self.junk += start
                end = self._inbuf.find(b"\x03", start)
                if end < 0:
                    del self._inbuf[:start]
                    break
                raw = bytes(self._inbuf[start : end + 1])
                del self._inbuf[: end + 1]
                self.host_frames.append(raw)
                body = raw[1:-1]
                if b"\x02" in body:
                    self.bad.append(f"STX inside a frame: {raw!r}")
                    continue
                try:
                    msg = check_host_frame(body)
                except ValueError as exc:
                    self.bad.append(str(exc))
                    continue
                self.can.send(msg)  # before the next host frame is read
                self.forwarded += 1
            self.lock.notify_all()
