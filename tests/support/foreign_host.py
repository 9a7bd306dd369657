"""A hand-made second host: DP0 commands to a drive that the supervisor under test did not
send, on the fake clock (a :class:`Timeline` node) or on python-can's virtual bus (its own
``can.Bus`` on the channel the supervisor uses, paced on the test's event loop)."""

from __future__ import annotations

import asyncio
import contextlib
import math
import time

import can

from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.generation import Generation
from tests.support.rig import Deaf

HOST = 2  # the seed's host address: a second copy of the supervisor uses it too


def moving_word(generation: Generation = Generation.G2021, rpm: int = 100) -> bytes:
    """SERVO and START on, both axes at ``rpm`` (0.2 min⁻¹ per LSB)."""
    layout = flags.layout(generation)
    inputs = layout.servo.both | layout.start.both
    return frames.encode_dp0_command(rpm * 5, rpm * 5, inputs)


def safe_word() -> bytes:
    return frames.encode_dp0_command(0, 0, 0)


class TimelineHost(Deaf):
    """A Timeline node that commands ``drive`` every ``period`` s from ``start`` to ``end``
    (then once the safe word, as a host that leaves politely does)."""

    def __init__(
        self,
        drive: int,
        start: float,
        end: float = math.inf,
        *,
        host: int = HOST,
        period: float = 0.02,
        word: bytes | None = None,
        request: bool = False,
    ) -> None:
        """``request``: a reader, sending ``word`` as requests (PF 0xEA), no farewell."""
        self.id = (ids.request_id if request else ids.dp0_command_id)(drive, host)
        self.farewell = [] if request else [(self.id, safe_word())]
        self.next, self.end, self.period = start, end, period
        self.word = word if word is not None else moving_word()
        self.sent: list[float] = []
        self.left = False

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        if now < self.next:
            return []
        if now >= self.end:
            self.next, self.left = math.inf, True
            return self.farewell
        self.sent.append(now)
        self.next += self.period
        return [(self.id, self.word)]

    def next_deadline(self) -> float:
        return self.next


class BusHost:
    """A second host on a virtual channel: :meth:`run` commands ``drive`` every
    ``period`` s until :meth:`leave`, then sends the safe word and closes its bus."""

    def __init__(
        self,
        channel: str,
        drive: int,
        *,
        host: int = HOST,
        period: float = 0.02,
        word: bytes | None = None,
    ) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.id = ids.dp0_command_id(drive, host)
        self.period = period
        self.word = word if word is not None else moving_word()
        self.first: float | None = None  # wall time (time.time) of the first frame
        self.count = 0
        self._leave = asyncio.Event()

    def _send(self, data: bytes) -> float:
        t = time.time()  # the virtual bus stamps its receivers' copies alike
        self.bus.send(can.Message(arbitration_id=self.id, data=data, is_extended_id=True))
        return t

    async def run(self) -> None:
        try:
            while not self._leave.is_set():
                t = self._send(self.word)
                self.count += 1
                if self.first is None:
                    self.first = t
                # paces the traffic; the test waits on conditions, not on this
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._leave.wait(), self.period)
            self._send(safe_word())
        finally:
            self.bus.shutdown()

    def leave(self) -> None:
        self._leave.set()
