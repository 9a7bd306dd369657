"""The thin asyncio layer: runs one sans-I/O machine (scheduler or simulator) on a bus.

Frames wait where python-can keeps them until a step reads them (scheduler/sources.py):
in the kernel behind the bus's file descriptor (SocketCAN, ``udp_multicast``, the
in-process simulator's drives' bus), else in a queue a reader thread fills (python-can's
``virtual`` bus, most USB adapters). Each step reads all that wait (up to
:data:`MAX_READ`), hands what they said to the owner (``after_step``), and only then
decides and sends its own frames. A single deadline timer (scheduler/timer.py: a timerfd,
which the kernel repeats while the deadlines keep one period) wakes the machine at its
next deadline; a frame wakes it only while the source is watched. Everything the machine
does therefore happens on the loop thread, one step at a time, on frames all read: a loop
that was late acts on every reply that came meanwhile at once (a robot's drives, each
waiting for its own reply, still send in one step).

``batch_s`` (the supervisor's pumps: :data:`READ_BATCH_S`): while the next deadline is at
most ``batch_s`` away the source is not watched — that step reads what came meanwhile.
Each frame keeps the time it came (its receive timestamp, bounded by the previous read),
and every decision the machine takes in a step follows a read, so nothing is decided on
stale frames; what waits is only the frames' delivery to the observers, by at most
``batch_s``. After a step that sent, the source is not watched either: the replies to
what it sent are read together by the next step, which the pump brings at the next turn
on the units' grid (``turns``: :meth:`Turns.read_by`) or ``batch_s`` later, whichever
comes first. At 100 Hz that is the units' next turn, so 4 units at 100 Hz wake the loop
once a period instead of once for the turn and once for its replies (or once per
reply): the CPU a wake-up costs is most of what an exchange costs (docs/performance.md,
sections 10 and 12; the scheduler puts up to the bus's ``units_per_turn`` units in one
turn). After a step that did not send, the pump watches while the next deadline is
further than ``batch_s``; and while a reply is overdue or the machine is in a
conversation (a parameter session, each answer bringing its next frame) it watches
after any step. The simulator's pumps (``batch_s`` 0) watch whenever their next
deadline is not now.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from typing import Protocol

import can

from abh3_supervisor.scheduler.bus_health import BusHealth, BusState
from abh3_supervisor.scheduler.sources import RETRY_S, FrameSource, source_for
from abh3_supervisor.scheduler.timer import DeadlineTimer

# the supervisor's pumps: frames may wait this long for the next step (one period at
# 100 Hz, so 4 units at 100 Hz wake the loop once a period); the observers see them at
# most this much later
READ_BATCH_S = 0.010
MAX_READ = 64  # frames read before a step: a flood cannot hold the loop (the rest next)
log = logging.getLogger(__name__)


class Machine(Protocol):
    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None: ...
    def poll(self, now: float) -> list[tuple[int, bytes]]: ...
    def next_deadline(self) -> float: ...
    def on_send_failed(self, arbitration_id: int) -> None: ...
    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None: ...


class Turns(Protocol):
    """What a batching pump asks of its machine's schedule (the bus scheduler's)."""

    def read_by(self, now: float) -> float:
        """When the frames that come from ``now`` on must be read: the next turn on the
        units' grid (as if every reply in flight had been read: the machine's own
        deadline waits for them, as it cannot know they came), or ``now`` — as they come
        — while a reply is overdue or a conversation goes on."""
        ...


class BusPump:
    def __init__(
        self,
        bus: can.BusABC,
        machine: Machine,
        *,
        name: str,
        channel: str,
        after_step: Callable[[], None] | None = None,
        recorder: can.Listener | None = None,
        on_fatal: Callable[[BaseException], None] | None = None,
        health: BusHealth | None = None,
        batch_s: float = 0.0,
        turns: Turns | None = None,
    ) -> None:
        self.bus, self.machine, self.name, self.channel = bus, machine, name, channel
        self.after_step = after_step
        self.recorder = recorder
        self.on_fatal = on_fatal
        self.loop = asyncio.get_running_loop()
        self._timer = DeadlineTimer(self.loop, self._step, repeating=True)
        self._source: FrameSource | None = None
        self._running = False
        self.batch_s = batch_s
        self.turns = turns
        self._read_at = 0.0  # when the bus was last read to the end
        self._last_t = 0.0  # the time given to the last frame read
        self._resume_at = 0.0  # a receive failed: reading rests until then
        self.frames_sent = 0
        self.frames_received = 0
        self.send_errors = 0
        self.last_send_error: str | None = None
        self.bus_errors = 0
        # bus-off, error-passive, a full queue: from error frames and send errors
        self.health = health if health is not None else BusHealth(name)

    def start(self) -> None:
        self._running = True
        self._source = source_for(self.bus, self.loop, self._step, self.on_error, self.name)
        self._read_at = self._last_t = self.loop.time()
        self._step()

    def stop(self) -> None:  # idempotent
        self._running = False
        self._timer.close()
        source, self._source = self._source, None
        if source is not None:
            source.stop()

    # ------------------------------------------------------------ receiving

    def _receive(self, msg: can.Message, now: float) -> bool:
        """One frame to the recorder and the machine; whether the machine took it."""
        if self.recorder is not None:
            self.recorder.on_message_received(msg)
        if msg.is_error_frame:
            self.bus_errors += 1
            self.health.on_error_frame(msg.arbitration_id, bytes(msg.data), now)
            self._health_changed()
            return False
        if not msg.is_extended_id:
            return False
        if msg.is_remote_frame or msg.is_fd:  # an ABH3 sends neither: never a reply
            why = "remote frame" if msg.is_remote_frame else "CAN FD frame"
            self.machine.on_bad_frame(msg.arbitration_id, now, why)
            return False
        self.frames_received += 1
        if self.health.state is not BusState.OK:  # only a bus in trouble watches for recovery
            self.health.on_received(now)
        self.machine.on_frame(msg.arbitration_id, bytes(msg.data), now)
        return True

    def _read(self) -> bool:
        """Every frame waiting on the bus (up to MAX_READ), in order, each at the time it
        came: its receive timestamp where that lies between the last read and now (a clock
        of the interface's own, or a stepped wall clock, is not trusted), else the time
        the source took it off the bus where it knows it, else now. Whether the machine
        took any."""
        now, source = self.loop.time(), self._source
        if now < self._resume_at or source is None:
            return False
        wall, since = time.time(), now - self._read_at
        self._read_at = now
        took = False
        take = source.take
        for _ in range(MAX_READ):
            try:
                msg = take(0)
            except Exception as exc:  # whatever the interface raises: rest, then again
                self._resume_at = now + RETRY_S
                self._watch(False)
                self.loop.call_at(self._resume_at, self._step)
                self.on_error(exc)
                return took
            if msg is None:
                return took
            age = wall - msg.timestamp
            if not 0.0 <= age <= since and (arrived := source.arrived) is not None:
                age = wall - arrived
            t = now - age if 0.0 <= age <= since else now
            self._last_t = t = max(t, self._last_t)
            took |= self._receive(msg, t)
        return took

    def _watch(self, on: bool) -> None:
        """Wake the loop when a frame waits, or leave the frames to the next step."""
        if self._source is not None:
            self._source.watch(on)

    def on_error(self, exc: Exception) -> None:
        """A receive failed (the interface went down): the bus's health says so once, as a
        notice; the source tries again after ``RETRY_S``."""
        self.bus_errors += 1
        code = getattr(exc, "error_code", None) or getattr(exc, "errno", None)
        self.health.on_send_error(code, f"receive failed: {exc}", self.loop.time())
        if self.health.changes:
            self._health_changed()
        else:
            log.debug("bus %s: receive failed again: %s", self.name, exc)

    def _health_changed(self) -> None:
        if self.health.changes and self.after_step is not None:
            self._guard(self.after_step)  # the owner drains and reports them

    # ------------------------------------------------------------ stepping

    def _guard(self, fn: Callable[..., object], *args: object) -> None:
        try:
            fn(*args)
        except Exception as exc:
            self._failed(exc)

    def _failed(self, exc: Exception) -> None:
        """A bug in a machine must end the run safely, not hang it."""
        log.exception("bus %s: internal error", self.name, exc_info=exc)
        if self.on_fatal is not None:
            self.on_fatal(exc)

    def _step(self) -> None:
        """A timer firing, or a frame waiting while watched: read what waits, then step."""
        if not self._running:
            return
        try:  # _guard's, inline: once per step
            self._step_unguarded(fed=self._read())
        except Exception as exc:
            self._failed(exc)
            # the timer may not fire again: a frame wakes us (the way out reads the
            # drives' answers to its stop frames)
            if self._running and self.loop.time() >= self._resume_at:
                self._watch(True)

    def _step_unguarded(self, fed: bool = False) -> None:
        """``fed``: frames were just given to the machine — what they said (another host
        on a drive, a unit back online) is acted on before this step's frames are decided
        and sent."""
        if fed and self.after_step is not None:
            self.after_step()
        now = self.loop.time()
        self._last_t = max(self._last_t, now)  # a frame read after this poll is not before it
        out = self.machine.poll(now)
        for arbitration_id, data in out:
            self.send(arbitration_id, data)
        if self.after_step is not None:
            self.after_step()
        deadline = self.machine.next_deadline()
        # a turn was sent: its replies are read together by the next turn's step, at most
        # a batch later, rather than each waking the loop as it comes (at 100 Hz: one
        # wake-up a period); the grid's time, not now's, or each turn would leave late by
        # the step's own latency
        hold = urgent = False  # urgent: a reply overdue, a conversation (read as they come)
        if self.batch_s > 0:
            read_by = now + self.batch_s
            if self.turns is not None:
                read_by = min(read_by, self.turns.read_by(now))
            urgent = read_by <= now
            hold = bool(out) and not urgent
            if hold:
                deadline = min(deadline, read_by)
        if not self._running or not math.isfinite(deadline):
            self._timer.cancel()
        else:
            self._timer.arm(deadline)
        if self._running and self.loop.time() >= self._resume_at:
            self._watch(urgent or (not hold and deadline - self.loop.time() > self.batch_s))

    def wake(self) -> None:
        """Step now (on the loop): new work was queued outside the schedule."""
        if self._running:
            self._timer.arm(self.loop.time())

    def take_late(self) -> float:
        """The most a timed step came after its deadline since the last call: a loop short
        of CPU (what slows the live view: service/view_pace.py)."""
        return self._timer.take_late()

    def send(self, arbitration_id: int, data: bytes) -> bool:
        """Send one frame now; a refused frame is counted and reported, never fatal."""
        msg = can.Message(
            arbitration_id=arbitration_id,
            data=data,
            is_extended_id=True,
            is_rx=False,
            timestamp=time.time(),
            channel=self.channel,
        )
        try:
            self.bus.send(msg, timeout=0)
        except can.CanError as exc:
            self.send_errors += 1
            self.last_send_error = str(exc) or type(exc).__name__
            code = getattr(exc, "error_code", None)
            self.health.on_send_error(code, self.last_send_error, self.loop.time())
            if math.log2(self.send_errors).is_integer():  # 1st, 2nd, 4th, 8th … failure
                log.warning("bus %s: send failed (%s); %d so far", self.name, exc, self.send_errors)
            self.machine.on_send_failed(arbitration_id)
            return False
        self.frames_sent += 1
        if self.health.state is not BusState.OK:
            self.health.on_sent(self.loop.time())
        if self.recorder is not None:
            self.recorder.on_message_received(msg)
        return True
