"""An observer of its own on a virtual CAN channel: every DP0 command to one drive, with
the time it was seen (protocol doc §3.1). It judges nothing; tests judge what it saw."""

from __future__ import annotations

import queue
import struct
import threading
import time

import can


def dp0_id(abh3: int, host: int = 2) -> int:
    return 0xEF << 16 | abh3 << 8 | host


class Observer:
    """Every DP0 command to one drive on the channel, with the time it was seen."""

    def __init__(self, channel: str, abh3: int = 1) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.ident = dp0_id(abh3)
        self.frames: queue.Queue[tuple[float, int]] = queue.Queue()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        while not self.done.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id & 0x3FFFFFF == self.ident:
                (word,) = struct.unpack_from("<I", bytes(msg.data), 4)
                self.frames.put((time.time(), word))

    def next_word(self, timeout: float) -> tuple[float, int]:
        return self.frames.get(timeout=timeout)

    def drain(self) -> None:
        while not self.frames.empty():
            self.frames.get_nowait()

    def close(self) -> None:
        self.done.set()
        self.thread.join(2)
        self.bus.shutdown()
