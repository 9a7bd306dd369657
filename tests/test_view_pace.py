"""The live view gives way while the buses' steps come late (service/view_pace.py)."""

from __future__ import annotations

import pytest

from abh3_supervisor.service.view_pace import CALM_S, LATE_S, MIN_HZ, STALE_S, ViewPace


class Loop:
    """A fake clock, the lateness the pumps report and whether the CPU quota held the
    process back, each taken (and forgotten) as asked."""

    def __init__(self) -> None:
        self.now = 100.0
        self.late = 0.0
        self.throttled = False

    def take(self) -> float:
        late, self.late = self.late, 0.0
        return late

    def held(self) -> bool:
        held, self.throttled = self.throttled, False
        return held


def paced() -> tuple[Loop, ViewPace]:
    """A pace whose first client has just had its first push."""
    loop = Loop()
    pace = ViewPace(loop.take, lambda: loop.now, loop.held)
    assert pace.period(0.1) == 0.1
    return loop, pace


def test_late_steps_before_anyone_watched_are_old_news() -> None:
    """The start-up's late steps, or those while no client was pushed to for a while."""
    loop = Loop()
    pace = ViewPace(loop.take, lambda: loop.now)
    loop.late = 0.5
    assert pace.period(0.1) == 0.1  # the first push: what came before it is not told
    loop.now += STALE_S + 0.5
    loop.late = 0.5
    assert pace.period(0.1) == 0.1  # nobody asked for that long
    loop.now += 0.1
    loop.late = 0.5
    assert pace.period(0.1) == pytest.approx(0.2)


def test_at_the_rate_asked_while_the_steps_come_on_time() -> None:
    loop, pace = paced()
    for _ in range(50):
        loop.late = LATE_S / 2  # a moment's wait is not a loop short of CPU
        assert pace.period(0.1) == 0.1
        loop.now += 0.1
    assert pace.to_json() is None


def test_each_late_step_halves_the_rate_down_to_the_slowest() -> None:
    loop, pace = paced()
    periods = []
    for late in (0.037, 0.02, 0.05, 0.09, 0.03):
        loop.late = late
        periods.append(pace.period(0.1))
        loop.now += periods[-1]
    assert periods == pytest.approx([0.2, 0.4, 0.8, 1 / MIN_HZ, 1 / MIN_HZ])
    # the step that last slowed it
    assert pace.to_json() == {"by": 16, "late_ms": 30.0, "quota": False}


def test_calm_brings_the_rate_back_one_step_at_a_time() -> None:
    loop, pace = paced()
    for _ in range(3):
        loop.late = 0.05
        pace.period(0.1)
    assert pace.slowdown == 8
    seen = []
    for _ in range(int(4 * CALM_S) + 5):  # pushes a second apart, no late step
        loop.now += 1.0
        seen.append(pace.period(0.1))
    assert sorted(set(seen), reverse=True) == pytest.approx([0.8, 0.4, 0.2, 0.1])
    # each step back waited CALM_S without a late step
    assert min(i for i, p in enumerate(seen) if p < 0.7) >= CALM_S - 1
    assert pace.to_json() is None


def test_a_late_step_in_the_calm_starts_it_again() -> None:
    loop, pace = paced()

    def after(seconds: int, late: float = 0.0) -> float:
        """The period of the last of pushes a second apart, the last told ``late``."""
        for i in range(seconds):
            loop.now += 1.0
            loop.late = late if i == seconds - 1 else 0.0
            period = pace.period(0.1)
        return period

    assert after(1, late=0.05) == pytest.approx(0.2)
    assert after(int(CALM_S) - 1, late=0.05) == pytest.approx(0.4)
    assert after(int(CALM_S) - 1) == pytest.approx(0.4)  # CALM_S since the last, not the first
    assert after(1) == pytest.approx(0.2)


def test_a_rate_slower_than_the_slowest_is_kept() -> None:
    loop, pace = paced()
    loop.late = 0.05
    assert pace.period(2.0) == 2.0  # 0.5 Hz asked: already slower than MIN_HZ
    assert pace.period(0.1) == pytest.approx(0.2)  # the other clients still give way


def test_the_cpu_quota_holding_the_process_back_slows_it_though_no_step_was_that_late() -> None:
    """A quota that holds the process back a few ms at a time: the steps fall short of
    LATE_S, yet the jitter a small board allows is gone (runtime/cgroups.py)."""
    loop, pace = paced()
    loop.late, loop.throttled = 0.004, True
    assert pace.period(0.1) == pytest.approx(0.2)
    assert pace.to_json() == {"by": 2, "late_ms": 4.0, "quota": True}
    loop.now += 0.2
    loop.late = 0.03  # then a step late past LATE_S: that is what it says
    assert pace.period(0.1) == pytest.approx(0.4)
    assert pace.to_json() == {"by": 4, "late_ms": 30.0, "quota": False}
