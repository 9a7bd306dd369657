"""A discrete-event CAN bus for sans-I/O machines, on a fake clock.

Links schedulers and simulated drives exactly as :class:`BusPump` does on a real bus
(step a machine after each frame it receives and at its deadlines) but deterministically
and without threads or sleeping. With a ``bitrate`` it also models the wire: one frame at
a time, each taking its exact stuffed bit time, and when the bus goes idle the lowest
identifier among the nodes' queued frames wins arbitration (each node sends in order).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from abh3_supervisor.core.wire import exact_bits
from abh3_supervisor.scheduler.pump import Machine


@dataclass
class _Node:
    machine: Machine
    after_step: Callable[[], None] | None
    queue: deque[tuple[int, bytes]] = field(default_factory=deque)


@dataclass(frozen=True, slots=True)
class WireFrame:
    start: float
    end: float
    node: int
    arbitration_id: int
    data: bytes


class Timeline:
    def __init__(self, bitrate: int | None = None, start: float = 0.0) -> None:
        self.bitrate = bitrate
        self.now = start
        self.nodes: list[_Node] = []
        self.frames: list[WireFrame] = []  # everything that crossed the wire, in order
        self._on_wire: tuple[int, int, bytes, float] | None = None
        self._busy_until = -math.inf
        self.busy_time = 0.0
        self.refusals: list[tuple[int, float, float]] = []  # (node, from, until)

    def refuse_sends(self, node: int, start: float, end: float) -> None:
        """The bus refuses ``node``'s frames from ``start`` until ``end`` (a full transmit
        queue, a loose connector): the machine is told, as :class:`BusPump` tells it."""
        self.refusals.append((node, start, end))

    def _refused(self, index: int) -> bool:
        return any(n == index and a <= self.now < b for n, a, b in self.refusals)

    def clock(self) -> float:
        return self.now

    def add(self, machine: Machine, after_step: Callable[[], None] | None = None) -> int:
        self.nodes.append(_Node(machine, after_step))
        return len(self.nodes) - 1

    def _step(self, index: int) -> None:
        node = self.nodes[index]
        for frame in node.machine.poll(self.now):
            if self.refusals and self._refused(index):
                node.machine.on_send_failed(frame[0])
            else:
                node.queue.append(frame)
        if node.after_step is not None:
            node.after_step()

    def _start_transmission(self) -> None:
        heads = [(n.queue[0][0], i) for i, n in enumerate(self.nodes) if n.queue]
        if not heads:
            return
        _, winner = min(heads)
        arbitration_id, data = self.nodes[winner].queue.popleft()
        duration = exact_bits(arbitration_id, data) / self.bitrate if self.bitrate else 0.0
        self._on_wire = (winner, arbitration_id, data, self.now)
        self._busy_until = self.now + duration
        self.busy_time += duration

    def _finish_transmission(self) -> None:
        assert self._on_wire is not None
        sender, arbitration_id, data, start = self._on_wire
        self._on_wire = None
        self.frames.append(WireFrame(start, self.now, sender, arbitration_id, data))
        for i, node in enumerate(self.nodes):
            if i != sender:
                node.machine.on_frame(arbitration_id, data, self.now)
                self._step(i)

    def run_until(self, end: float) -> None:
        """Advance the clock to ``end``, processing every event on the way."""
        for i in range(len(self.nodes)):
            self._step(i)
        stuck, last = 0, self.now
        while True:
            stuck = stuck + 1 if self.now == last else 0
            last = self.now
            if stuck > 100_000:
                raise RuntimeError(f"no progress at t={self.now}: a deadline does not advance")
            if self._on_wire is None:
                self._start_transmission()
            wire = self._busy_until if self._on_wire is not None else math.inf
            deadline = min((n.machine.next_deadline() for n in self.nodes), default=math.inf)
            t = min(wire, deadline)
            if t > end:
                self.now = end
                return
            self.now = max(self.now, t)
            if self._on_wire is not None and self._busy_until <= self.now:
                self._finish_transmission()
                continue
            for i, node in enumerate(self.nodes):
                if node.machine.next_deadline() <= self.now:
                    self._step(i)
