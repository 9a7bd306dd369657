"""The supervisor's pump on a bus with a file descriptor (``batch_s``, scheduler/pump.py):
it reads every waiting frame before each step, leaves a turn's replies to the next step
(at most ``batch_s`` later), watches the bus only while its next deadline is further than
``batch_s``, and gives each frame the time it came.

The loop and the timer are fakes with a clock the test sets: nothing here waits.
"""

from __future__ import annotations

import asyncio
import collections
import math
import time
from collections.abc import Callable, Iterator
from typing import ClassVar

import can
import pytest

from abh3_supervisor.scheduler import sources
from abh3_supervisor.scheduler.pump import MAX_READ, READ_BATCH_S, BusPump
from abh3_supervisor.scheduler.sources import ThreadReader
from tests.support.rig import Deaf

BATCH = READ_BATCH_S  # one period at 100 Hz


class Clocks:
    """The loop's monotonic clock and the wall clock, which the test moves together."""

    def __init__(self) -> None:
        self.mono, self.wall = 100.0, 1_700_000_000.0

    def advance(self, dt: float) -> None:
        self.mono += dt
        self.wall += dt


class FakeLoop:
    def __init__(self, clocks: Clocks) -> None:
        self.clocks = clocks
        self.readers: dict[int, Callable[[], None]] = {}
        self.later: list[tuple[float, Callable[[], None]]] = []

    def time(self) -> float:
        return self.clocks.mono

    def add_reader(self, fd: int, callback: Callable[[], None]) -> None:
        self.readers[fd] = callback

    def remove_reader(self, fd: int) -> None:
        del self.readers[fd]

    def call_at(self, when: float, callback: Callable[[], None]) -> None:
        self.later.append((when, callback))


class FakeTimer:
    def __init__(self) -> None:
        self.when: float | None = None

    def arm(self, when: float) -> None:
        self.when = when if self.when is None else min(self.when, when)

    def cancel(self) -> None:
        self.when = None

    def close(self) -> None:
        self.when = None


class QueueBus(can.BusABC):
    """Frames waiting on a file descriptor; ``recv(0)`` hands them over one by one."""

    made: ClassVar[list[QueueBus]] = []

    def __init__(self) -> None:
        super().__init__(channel="q")
        QueueBus.made.append(self)
        self.waiting: collections.deque[can.Message] = collections.deque()
        self.sent: list[can.Message] = []
        self.fail = False

    def fileno(self) -> int:
        return 42

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail:
            raise can.CanOperationError("Network is down")
        return (self.waiting.popleft() if self.waiting else None), False


@pytest.fixture(autouse=True)
def _shut() -> Iterator[None]:
    yield
    while QueueBus.made:
        QueueBus.made.pop().shutdown()


class Machine(Deaf):
    """Sends a frame at each deadline of a fixed period; records what it was fed."""

    def __init__(self, period: float, start: float) -> None:
        self.period, self.due = period, start
        self.fed: list[tuple[int, float]] = []
        self.polled: list[tuple[float, int]] = []  # when, frames fed by then

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        self.fed.append((arbitration_id, now))

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        self.polled.append((now, len(self.fed)))
        if now < self.due:
            return []
        while self.due <= now:
            self.due += self.period
        return [(0x100, bytes(8))]

    def next_deadline(self) -> float:
        return self.due


def frame(ident: int, timestamp: float) -> can.Message:
    return can.Message(
        arbitration_id=ident, data=bytes(8), is_extended_id=True, timestamp=timestamp
    )


def rounded(pairs: list[tuple[int, float]] | list[tuple[float, int]]) -> list[tuple[float, float]]:
    """Times to the microsecond (the fake clocks add floats)."""
    return [(round(a, 6), round(b, 6)) for a, b in pairs]


def pump_for(
    period: float, monkeypatch: pytest.MonkeyPatch
) -> tuple[BusPump, QueueBus, Machine, FakeLoop, FakeTimer, Clocks]:
    clocks = Clocks()
    monkeypatch.setattr(time, "time", lambda: clocks.wall)  # the pump's wall clock
    monkeypatch.setattr(sources, "WATCH_SET", False)  # the watch is the fake loop's reader
    bus, machine = QueueBus(), Machine(period, clocks.mono)

    async def build() -> BusPump:
        return BusPump(bus, machine, name="b", channel="q", batch_s=BATCH)

    pump = asyncio.run(build())
    loop, timer = FakeLoop(clocks), FakeTimer()
    pump.loop, pump._timer = loop, timer  # type: ignore[assignment]
    pump.start()
    return pump, bus, machine, loop, timer, clocks


def thread_pump_for(
    period: float, monkeypatch: pytest.MonkeyPatch
) -> tuple[BusPump, ThreadReader, Machine, Clocks]:
    """The pump on a bus without a file descriptor; the test plays its reader thread,
    putting frames in the queue itself."""

    def no_fd(self: QueueBus) -> int:
        raise NotImplementedError

    monkeypatch.setattr(QueueBus, "fileno", no_fd)
    monkeypatch.setattr(ThreadReader, "start", lambda self: None)
    pump, _, machine, _, _, clocks = pump_for(period, monkeypatch)
    assert isinstance(pump._source, ThreadReader)
    return pump, pump._source, machine, clocks


def test_a_near_deadline_leaves_the_frames_to_the_step_which_reads_them_first(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pump, bus, machine, loop, timer, clocks = pump_for(0.0025, monkeypatch)
    assert len(bus.sent) == 1 and timer.when == pytest.approx(clocks.mono + 0.0025)
    assert loop.readers == {}  # the next step is 2.5 ms away: nobody watches the bus
    clocks.advance(0.0005)  # the reply comes 0.5 ms after the command; nothing wakes
    bus.waiting.append(frame(0x200, clocks.wall))
    clocks.advance(0.002)  # the timer fires
    pump._step()
    # the reply was fed before the step decided anything, at the time it came
    assert rounded(machine.fed) == [(0x200, 100.0005)]
    assert rounded(machine.polled[-1:]) == [(100.0025, 1)]
    assert len(bus.sent) == 2 and loop.readers == {}


def fire(pump: BusPump, timer: FakeTimer) -> None:
    """The timer fires: its expiry is spent, the step arms it anew."""
    timer.when = None
    pump._step()


def test_a_turns_replies_are_read_together_a_batch_later_then_a_far_deadline_watches_the_bus(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pump, bus, machine, loop, timer, clocks = pump_for(0.050, monkeypatch)  # 20 Hz
    # the start sent a frame: its replies are read a batch later, nothing wakes before
    assert loop.readers == {} and timer.when == pytest.approx(clocks.mono + BATCH)
    for _ in range(3):  # replies in three bursts: none wakes the loop
        clocks.advance(0.0005)
        bus.waiting.append(frame(0x200, clocks.wall))
    clocks.advance(BATCH - 0.0015)
    fire(pump, timer)  # one wake-up reads them all, each at the time it came
    assert rounded(machine.fed) == [(0x200, 100.0005), (0x200, 100.001), (0x200, 100.0015)]
    assert len(bus.sent) == 1 and timer.when == pytest.approx(100.050)
    assert list(loop.readers) == [42]  # 40 ms to the next step: another frame must wake us
    clocks.advance(0.001)
    bus.waiting.append(frame(0x300, clocks.wall))
    loop.readers[42]()  # the loop saw the bus readable
    assert rounded(machine.fed[-1:]) == [(0x300, 100.011)]
    assert machine.polled[-1][1] == 4  # stepped after the frame
    pump.stop()
    assert loop.readers == {}


def test_at_100_hz_the_loop_wakes_once_a_period_and_each_step_reads_the_last_turns_replies(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The next turn is a batch away: the turn's replies wait for it, never watched."""
    pump, bus, machine, loop, timer, clocks = pump_for(0.010, monkeypatch)
    start = clocks.mono
    for n in range(1, 6):
        assert loop.readers == {} and timer.when == pytest.approx(start + n * 0.010)
        clocks.advance(0.0007)  # the drive answers the turn
        bus.waiting.append(frame(0x200, clocks.wall))
        answered = clocks.mono
        assert timer.when is not None
        clocks.advance(timer.when - clocks.mono)  # the timer fires at the next turn
        fire(pump, timer)
        # its reply fed before that step decided anything, at the time it came
        assert machine.fed[-1][0] == 0x200 and machine.fed[-1][1] == pytest.approx(answered)
        assert machine.polled[-1][0] == pytest.approx(start + n * 0.010)
        assert machine.polled[-1][1] == n
    assert len(bus.sent) == 6 and len(machine.polled) == 6  # one step a period, no other


class Schedule:
    """The scheduler's ``read_by`` (pump.Turns), as a test sets it."""

    def __init__(self, turn: float) -> None:
        self.turn, self.urgent = turn, False

    def read_by(self, now: float) -> float:
        return now if self.urgent else self.turn


def test_the_replies_are_read_by_the_next_turn_on_the_grid_not_a_batch_after_a_late_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A step runs a little after its deadline; its turn's replies held for ``now +
    batch`` would bring every turn later by as much (a 100 Hz unit ran at 97 Hz)."""
    pump, _, _, loop, timer, clocks = pump_for(0.020, monkeypatch)
    start = clocks.mono
    pump.turns = Schedule(start + 0.030)  # another unit's turn 10 ms after this one's
    clocks.advance(0.020 + 0.0004)  # the timer's step at +20 ms runs 0.4 ms late
    fire(pump, timer)
    assert timer.when == pytest.approx(start + 0.030)  # the grid's 10 ms later, not 10.4
    assert loop.readers == {}


def test_a_reply_overdue_or_a_conversation_is_read_as_it_comes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A parameter session's every answer brings its next frame, and a late reply holds
    its unit's command: held for the next turn, each would wait a period."""
    pump, bus, machine, loop, timer, clocks = pump_for(0.010, monkeypatch)
    assert loop.readers == {}  # the start's turn: its replies held for the next step
    schedule = pump.turns = Schedule(clocks.mono + 0.020)
    schedule.urgent = True
    clocks.advance(0.010)
    fire(pump, timer)  # a turn that sent, in a conversation: watched at once
    assert list(loop.readers) == [42] and timer.when == pytest.approx(clocks.mono + 0.010)
    clocks.advance(0.0004)
    bus.waiting.append(frame(0x1CEB0201, clocks.wall))  # the drive's answer wakes the loop
    loop.readers[42]()  # a step that sent nothing: still watched
    assert machine.fed[-1][0] == 0x1CEB0201 and machine.fed[-1][1] == pytest.approx(clocks.mono)
    assert list(loop.readers) == [42]
    schedule.urgent = False
    assert timer.when is not None
    clocks.advance(timer.when - clocks.mono)
    schedule.turn = clocks.mono + 0.010
    fire(pump, timer)  # nothing urgent: the turn's replies are held again
    assert loop.readers == {}


def test_a_pump_that_does_not_batch_watches_at_once_after_it_sent(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("tests.test_pump_batch.BATCH", 0.0)  # the simulator's pumps
    _, _, _, loop, timer, clocks = pump_for(0.010, monkeypatch)
    assert list(loop.readers) == [42] and timer.when == pytest.approx(clocks.mono + 0.010)


def test_a_frame_keeps_its_time_only_within_the_time_since_the_last_read(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pump, bus, machine, _, _, clocks = pump_for(0.0025, monkeypatch)
    clocks.advance(0.002)
    bus.waiting.extend(
        [
            frame(1, clocks.wall - 0.001),  # came 1 ms ago: kept
            frame(2, clocks.wall - 60.0),  # an interface's own clock, or a stepped wall: now
            frame(3, clocks.wall + 5.0),  # from the future: now
            frame(4, clocks.wall - 0.0015),  # earlier than the frame before it: not before it
        ]
    )
    pump._step()
    assert rounded(machine.fed) == [(1, 100.001), (2, 100.002), (3, 100.002), (4, 100.002)]


def test_a_flood_is_read_a_batch_at_a_time(monkeypatch: pytest.MonkeyPatch) -> None:
    pump, bus, machine, _, _, clocks = pump_for(0.0025, monkeypatch)
    bus.waiting.extend(frame(0x200, clocks.wall) for _ in range(MAX_READ + 10))
    clocks.advance(0.0025)
    pump._step()
    assert len(machine.fed) == MAX_READ and len(bus.waiting) == 10  # the rest: next step
    clocks.advance(0.0025)
    pump._step()
    assert len(machine.fed) == MAX_READ + 10


def test_a_receive_that_fails_rests_then_reads_again(monkeypatch: pytest.MonkeyPatch) -> None:
    pump, bus, machine, loop, timer, clocks = pump_for(0.050, monkeypatch)
    clocks.advance(BATCH)
    fire(pump, timer)  # the start's replies read: the bus watched from here on
    notes: list[Exception] = []
    monkeypatch.setattr(pump, "on_error", notes.append)
    bus.fail = True
    loop.readers[42]()
    assert len(notes) == 1 and loop.readers == {}  # not watched while it rests
    ((when, again),) = loop.later
    clocks.advance(0.002)
    pump._step()  # a timer step meanwhile does not try the bus
    assert len(notes) == 1 and loop.readers == {}
    bus.fail = False
    bus.waiting.append(frame(0x200, clocks.wall))
    clocks.mono = when
    again()
    assert [i for i, _ in machine.fed] == [0x200]
    assert timer.when is not None  # watched again as before: only while the step is far
    assert (42 in loop.readers) == (timer.when - clocks.mono > BATCH)


def test_what_the_frames_said_is_acted_on_before_the_step_sends(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Another host's frame read at a step must stop the unit before that step's frame
    goes: the owner's reaction (the Supervisor's dispatch, ``after_step``) comes first."""
    pump, bus, machine, _, _, clocks = pump_for(0.0025, monkeypatch)
    seen: list[tuple[int, int, int]] = []  # at each dispatch: frames fed, polls, frames sent
    pump.after_step = lambda: seen.append((len(machine.fed), len(machine.polled), len(bus.sent)))
    clocks.advance(0.001)
    bus.waiting.append(frame(0x0CEF0102, clocks.wall))  # a foreign command, say
    clocks.advance(0.0015)
    polled, sent = len(machine.polled), len(bus.sent)
    pump._step()
    assert seen[0] == (1, polled, sent)  # the frame dispatched, nothing polled or sent yet
    assert len(bus.sent) == sent + 1 and seen[-1][2] == sent + 1  # then the step's own


def test_after_a_step_that_failed_the_bus_is_watched_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A bug in a machine ends the run; the way out must still hear the drives' answers
    to its stop frames, though the timer may never fire again."""
    pump, _, machine, loop, _, clocks = pump_for(0.0025, monkeypatch)
    failures: list[BaseException] = []
    pump.on_fatal = failures.append
    assert loop.readers == {}
    monkeypatch.setattr(machine, "poll", lambda now: 1 / 0)
    clocks.advance(0.0025)
    pump._step()
    assert len(failures) == 1 and list(loop.readers) == [42]


def test_a_frame_read_after_a_poll_is_not_timed_before_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pump, bus, machine, _, _, clocks = pump_for(0.0025, monkeypatch)
    start = clocks.mono
    clocks.advance(0.0025)
    bus.waiting.append(frame(0x200, clocks.wall - 0.0024))  # stamped before the last poll
    pump._step()
    assert machine.fed[0][1] >= start  # the first step polled at start: never before it


def test_without_a_file_descriptor_the_step_reads_the_reader_threads_queue_first(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """python-can's virtual bus, a USB adapter: a late loop finds both drives' replies
    waiting and feeds them before the step, so both units' commands leave in it (python-
    can's Notifier stepped once per reply: the first unit's command went a step early)."""

    pump, source, machine, clocks = thread_pump_for(0.0025, monkeypatch)
    clocks.advance(0.001)
    source.frames.extend([(frame(i, clocks.wall), clocks.wall) for i in (0x201, 0x203)])
    clocks.advance(0.0015)
    polled = len(machine.polled)
    pump._step()
    assert rounded(machine.fed) == [(0x201, 100.001), (0x203, 100.001)]
    assert machine.polled[polled:] == [(clocks.mono, 2)]  # one step, after both
    pump.stop()


def test_a_frame_an_interface_stamped_with_its_own_clock_is_timed_when_the_reader_took_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """PCAN without ``uptime`` stamps seconds since boot: the reader thread's own time of
    the frame, not the step's, is when it came."""

    pump, source, machine, clocks = thread_pump_for(0.0025, monkeypatch)
    clocks.advance(0.0005)
    source.frames.append((frame(0x201, 8123.25), clocks.wall))  # since boot; taken now
    clocks.advance(0.002)
    pump._step()
    assert rounded(machine.fed) == [(0x201, 100.0005)]
    pump.stop()


def test_a_step_that_sent_with_nothing_due_after_it_reads_a_batch_later_then_watches(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """No deadline left: the replies are read by a step the pump arms itself, and from
    then on the bus is watched (no timer will bring another read)."""
    pump, bus, _, loop, timer, clocks = pump_for(math.inf, monkeypatch)  # one frame, then none
    assert len(bus.sent) == 1 and timer.when == pytest.approx(clocks.mono + BATCH)
    assert loop.readers == {}
    clocks.advance(BATCH)
    fire(pump, timer)
    assert timer.when is None and list(loop.readers) == [42]
