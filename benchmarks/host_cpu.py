"""2. Host CPU per DP0 exchange: our whole stack next to bare python-can.

Both sides talk to the same echo drive (a python-can handle in a thread of this process
that answers every DP0 command at once) on python-can's ``virtual`` interface, and both
are timed with process CPU time, so the echo's own cost is in both figures alike.

* **bare python-can** — build a message, ``send``, ``recv`` until the reply: the least any
  Python host can do per exchange on this interface;
* **ours** — the real path: set a new setpoint (through the arbitration, the motion gate's
  checks and the limits, then encoded), scheduler poll, pump send, the reply's hand-over
  to the event loop, match + decode, state update, flag bookkeeping, and dispatch to one
  subscribed observer (the hook path plugins use);
* **ours, the setpoint set once** — the same with the observer only counting: what an
  exchange costs where the setpoints come slower than the exchanges (a joystick at
  20–50 Hz, ``cmd_vel`` at 10–50 Hz, drives at 100 Hz), and so what a new setpoint adds;
* **an event loop alone** — asyncio and the pump's hand-over of the reply to the loop
  (scheduler/sources.py), sending the next command from the wake-up: no scheduler, no
  supervisor. What any event-loop host pays here before doing anything of its own, so
  that the three rows part the cost into the loop's, the exchange's and the setpoint's.

:func:`interleaved` runs them free (the threads where the kernel puts them: the figure
the target is on) or ``pinned`` to one core. Free, each exchange is two wake-ups across
cores (the echo drive's thread and ours), which cost bare python-can as much as its own
work on this VM and move with the machine; on one core they are gone, and what is left
is each side's own work — ours is then seen whole, and its median moves by about 1 %.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
import time
from collections.abc import Callable, Iterator

import can

from abh3_supervisor.config.model import BroadcastConfig, BusConfig, Config, UnitConfig
from abh3_supervisor.core.commands import VelocityCommand
from abh3_supervisor.core.inputs import InputSource
from abh3_supervisor.core.supervisor import Supervisor, SupervisorEvent
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.scheduler.core import FeedbackEvent
from abh3_supervisor.scheduler.pump import BusPump
from abh3_supervisor.scheduler.sources import source_for

CMD_ID, REPLY_ID = ids.dp0_command_id(1, 2), ids.dp0_reply_id(1, 2)
_L23 = flags.LAYOUT_2023
# a 2023 drive's reply reporting SERVO and START on both axes (and the data select it was
# given): the robot decision finds it ready, so every exchange runs the setpoint path
READY_REPLY = frames.encode_dp0_reply_2023(0, 0, _L23.servo.both | _L23.start.both | 0x70)


class EchoDrive:
    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.reply = can.Message(arbitration_id=REPLY_ID, data=READY_REPLY, is_extended_id=True)

    def __enter__(self) -> EchoDrive:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.bus.shutdown()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is not None and msg.arbitration_id == CMD_ID:
                self.bus.send(self.reply)


def bare(exchanges: int) -> float:
    """CPU seconds per exchange for a plain python-can send/recv loop."""
    with EchoDrive("bench-bare"):
        bus = can.Bus(interface="virtual", channel="bench-bare")
        try:
            start = time.process_time()
            for i in range(exchanges):
                data = frames.encode_dp0_command(i & 0x7FFF, 0, 0)
                bus.send(can.Message(arbitration_id=CMD_ID, data=data, is_extended_id=True))
                while (msg := bus.recv(1.0)) is not None and msg.arbitration_id != REPLY_ID:
                    pass
            return (time.process_time() - start) / exchanges
        finally:
            bus.shutdown()


class _Input(InputSource):
    """The observer's input source: it submits on the loop (as the control socket's
    clients' do), so it needs no feed."""

    def start(self, feed: object) -> None:
        pass

    def stop(self) -> None:
        pass


def ours(exchanges: int, *, new_setpoint: bool = True) -> float:
    """CPU seconds per exchange through scheduler, pump, supervisor and one observer,
    which sets a new setpoint at every reply (``new_setpoint``), else at the first only:
    an input source's command in the arbitration, the one way a setpoint enters."""
    unit = UnitConfig(
        name="u",
        bus="b",
        protocol=Generation.G2023,
        command_rate_hz=1e6,
        broadcast=BroadcastConfig(mask=0),
    )
    config = Config(file="bench", buses={"b": BusConfig(name="b")}, units={"u": unit})

    async def run() -> float:
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        sup = Supervisor(config, clock=loop.time)
        for text in ("SERVO ON ON", "START ON ON"):  # switched on: the robot may move
            sup.apply_text("u", text)
        sup.arbiter.add(_Input("bench", ("u",)))
        count = 0

        def observer(event: SupervisorEvent) -> None:
            nonlocal count
            if not isinstance(event, FeedbackEvent):
                return
            count += 1
            if new_setpoint or count == 1:
                sup.arbiter.submit_now("bench", VelocityCommand(float(count % 1000), 0.0))
            if count >= exchanges and not done.done():
                done.set_result(None)

        sup.subscribe(observer)
        with EchoDrive("bench-ours"):
            bus = can.Bus(interface="virtual", channel="bench-ours")
            pump = BusPump(
                bus,
                sup.schedulers["b"],
                name="b",
                channel="bench-ours",
                after_step=lambda: sup.dispatch("b"),
            )
            cpu = await _cpu_until(done, pump.start, pump.stop)
            bus.shutdown()
        return cpu / count

    return asyncio.run(run())


def event_loop(exchanges: int) -> float:
    """CPU seconds per exchange for an event loop that only sends the next command when
    the pump's source hands it the reply."""

    async def run() -> float:
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        count = 0
        with EchoDrive("bench-loop"):
            bus = can.Bus(interface="virtual", channel="bench-loop")

            def send() -> None:
                data = frames.encode_dp0_command(count & 0x7FFF, 0, 0)
                bus.send(can.Message(arbitration_id=CMD_ID, data=data, is_extended_id=True))

            def woken() -> None:
                nonlocal count
                while (got := source.recv()) is not None:
                    if got[0].arbitration_id != REPLY_ID:
                        continue
                    count += 1
                    if count >= exchanges:
                        if not done.done():
                            done.set_result(None)
                        return
                    send()

            source = source_for(bus, loop, woken, print, "bench-loop")
            source.watch(True)
            cpu = await _cpu_until(done, send, source.stop)
            bus.shutdown()
        return cpu / count

    return asyncio.run(run())


async def _cpu_until(
    done: asyncio.Future[None], start: Callable[[], None], stop: Callable[[], None]
) -> float:
    """Process CPU seconds from ``start()`` until ``done``; ``stop()`` after."""
    begin = time.process_time()
    start()
    await done
    cpu = time.process_time() - begin
    stop()
    return cpu


@contextlib.contextmanager
def _on_one_core(pinned: bool) -> Iterator[None]:
    """This thread, and the threads it starts meanwhile, on one core of those it may use
    (the last: the first takes the machine's interrupts), if ``pinned``."""
    allowed = os.sched_getaffinity(0)
    if not pinned or len(allowed) < 2:
        yield
        return
    os.sched_setaffinity(0, {max(allowed)})
    try:
        yield
    finally:
        os.sched_setaffinity(0, allowed)


def interleaved(
    exchanges: int, runs: int, *, pinned: bool = False
) -> tuple[list[float], list[float], list[float], list[float]]:
    """``runs`` rounds of ours, ours with the setpoint set once, the event loop alone, then
    bare (CPU seconds per exchange), so that each round shares the machine's state of the
    moment: the four lists, run by run. ``pinned``: every thread of them on one core."""
    with _on_one_core(pinned):
        rounds = [
            (
                ours(exchanges),
                ours(exchanges, new_setpoint=False),
                event_loop(exchanges),
                bare(exchanges),
            )
            for _ in range(runs)
        ]
    new, once, alone, plain = (list(column) for column in zip(*rounds, strict=True))
    return new, once, alone, plain
