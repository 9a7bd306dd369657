"""The pump's deadline timer: fires once per arming, can be re-armed and cancelled."""

from __future__ import annotations

import asyncio

import pytest

from abh3_supervisor.core.timing import next_on_grid
from abh3_supervisor.scheduler import timer as timer_module
from abh3_supervisor.scheduler.timer import DeadlineTimer

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes


@pytest.mark.parametrize("precise", [True, False], ids=["timerfd", "call_at"])
def test_fires_at_the_deadline_and_not_after_cancel(
    precise: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if not precise:
        monkeypatch.setattr(timer_module, "_LIBC", None)

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        fired: list[float] = []
        done = loop.create_future()

        def callback() -> None:
            fired.append(loop.time())
            if not done.done():
                done.set_result(None)

        t = DeadlineTimer(loop, callback)
        if precise and timer_module._LIBC is None:
            pytest.skip("no timerfd on this platform")
        assert t.precise is precise
        t.arm(loop.time() + 10)
        deadline = loop.time() + 0.02
        t.arm(deadline)  # an earlier deadline replaces the armed one
        t.arm(loop.time() + 5)  # a later one keeps it (the callback re-arms when it fires)
        await asyncio.wait_for(done, 5)
        assert fired[0] >= deadline - 1e-4 and len(fired) == 1
        t.arm(loop.time() + 0.01)
        t.cancel()
        other = loop.create_future()
        loop.call_later(0.05, other.set_result, None)  # a later event proves no firing
        await other
        assert len(fired) == 1
        t.close()

    asyncio.run(scenario())


def _repeating(gaps: list[float], firings: int) -> tuple[list[float], int]:
    """A repeating timer whose callback arms the next deadline ``gaps`` apart (cycled):
    how early or late each firing came (loop time − deadline), and how many times the
    kernel was asked to set the timer."""
    if timer_module._LIBC is None:
        pytest.skip("no timerfd on this platform")
    set_calls = 0
    settime = DeadlineTimer._settime

    def counted(self: DeadlineTimer, seconds: int, nanoseconds: int, interval: int) -> None:
        nonlocal set_calls
        set_calls += 1
        settime(self, seconds, nanoseconds, interval)

    async def scenario() -> list[float]:
        loop = asyncio.get_running_loop()
        offsets: list[float] = []
        done = loop.create_future()
        deadline = loop.time() + 0.01

        def callback() -> None:
            nonlocal deadline
            offsets.append(loop.time() - deadline)
            if len(offsets) == firings:
                done.set_result(None)
                return  # not re-armed: it must not fire again
            deadline += gaps[len(offsets) % len(gaps)]
            t.arm(deadline)

        t = DeadlineTimer(loop, callback, repeating=True)
        t.arm(deadline)
        await asyncio.wait_for(done, 10)
        quiet = loop.create_future()
        loop.call_later(0.05, quiet.set_result, None)  # a repetition would come in this
        await quiet
        t.close()
        return offsets

    with pytest.MonkeyPatch.context() as m:
        m.setattr(DeadlineTimer, "_settime", counted)
        offsets = asyncio.run(scenario())
    return offsets, set_calls


def test_a_periodic_schedule_is_repeated_by_the_kernel_and_never_late() -> None:
    offsets, set_calls = _repeating([0.004], 40)
    assert len(offsets) == 40  # and none after the callback stopped arming
    # never before its deadline by more than the repetition's allowed lead (2 µs)
    assert min(offsets) >= -(timer_module._SLACK_NS + 40 * timer_module._DRIFT_NS) / 1e9
    # armed once, repeated from the first firing on; one more to stop it at the end
    assert set_calls <= 4


def test_an_irregular_schedule_is_armed_each_time_and_never_early() -> None:
    offsets, set_calls = _repeating([0.002, 0.007], 20)
    assert len(offsets) == 20
    # a guess that does not fit is set again, not kept: no firing before its deadline
    assert min(offsets) >= -(timer_module._SLACK_NS / 1e9)
    assert set_calls >= 19


def test_a_timer_not_asked_to_repeat_fires_once_per_arming() -> None:
    if timer_module._LIBC is None:
        pytest.skip("no timerfd on this platform")

    async def scenario() -> int:
        loop = asyncio.get_running_loop()
        fired: list[float] = []
        t = DeadlineTimer(loop, lambda: fired.append(loop.time()))
        for _ in range(3):
            t.arm(loop.time() + 0.003)
            gone = loop.create_future()
            loop.call_later(0.02, gone.set_result, None)
            await gone
        assert t._interval_ns == 0
        t.close()
        return len(fired)

    assert asyncio.run(scenario()) == 3


def test_a_later_deadline_from_outside_the_callback_keeps_the_repetition() -> None:
    """A frame that moves the deadline later (the simulator's drives: their command-zero
    watch, at every command) costs no system call: the repetition fires early, and its
    callback sets the timer for the deadline then."""
    if timer_module._LIBC is None:
        pytest.skip("no timerfd on this platform")
    calls: list[int] = []
    kept: list[bool] = []

    async def scenario() -> tuple[list[float], float]:
        loop = asyncio.get_running_loop()
        fired: list[float] = []
        done = loop.create_future()
        late = loop.time() + 0.05

        def outside() -> None:  # a frame's step: not the timer's callback
            before = len(calls)
            t.arm(loop.time() + 0.5)  # later than the repetition: kept
            kept.append(len(calls) == before)

        def callback() -> None:
            fired.append(loop.time())
            if len(fired) < 3:
                t.arm(loop.time() + 0.004)  # a period: the kernel repeats it
                if len(fired) == 2:
                    loop.call_soon(outside)
            elif len(fired) == 3:
                t.arm(late)  # the repetition came early: set for the deadline now
            else:
                done.set_result(None)

        t = DeadlineTimer(loop, callback, repeating=True)
        settime = t._settime

        def counted(seconds: int, nanoseconds: int, interval: int) -> None:
            calls.append(interval)
            settime(seconds, nanoseconds, interval)

        t._settime = counted  # type: ignore[method-assign]
        t.arm(loop.time() + 0.004)
        await asyncio.wait_for(done, 5)
        t.close()
        return fired, late

    fired, late = asyncio.run(scenario())
    assert kept == [True]
    assert fired[-1] >= late - 1e-4  # the late deadline was kept, never before it


def test_a_grid_keeps_its_phase_after_a_stall() -> None:
    assert next_on_grid(1.0, 0.01, 1.005) == pytest.approx(1.01)  # on time
    # a stall of 3.7 periods: the next point of the same grid, missed ones skipped
    assert next_on_grid(1.0, 0.01, 1.037) == pytest.approx(1.04)
    assert next_on_grid(1.0, 0.01, 1.04) == pytest.approx(1.05)  # exactly on a point: the next


@pytest.mark.parametrize("precise", [True, False], ids=["timerfd", "call_at"])
def test_a_firing_says_how_late_it_came_until_taken(
    precise: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The live view gives way when the loop runs late (service/view_pace.py): a deadline
    already past when the timer is serviced is reported as late by as much, once."""
    if not precise:
        monkeypatch.setattr(timer_module, "_LIBC", None)

    async def scenario() -> tuple[float, float, float]:
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        t = DeadlineTimer(loop, lambda: done.set_result(loop.time()))
        if precise and timer_module._LIBC is None:
            pytest.skip("no timerfd on this platform")
        before = t.late_s
        deadline = loop.time() - 0.03  # the loop comes to it 30 ms after it fell due
        t.arm(deadline)
        fired = await asyncio.wait_for(done, 5)
        late = t.take_late()
        t.close()
        return before, late - (fired - deadline), t.take_late()

    before, error, after = asyncio.run(scenario())
    assert before == 0.0
    assert abs(error) < 0.005  # as late as the callback saw it (both read the same clock)
    assert after == 0.0  # taken: forgotten
