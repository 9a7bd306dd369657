"""Input arbitration on a fake clock: priority, recency, staleness and release mean zero."""

from __future__ import annotations

from abh3_supervisor.inputs import (
    ZERO,
    InputArbiter,
    InputCommand,
    InputFeed,
    InputSource,
    Twist,
    VelocityYX,
)


class Source(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


def arbiter() -> tuple[InputArbiter, list[tuple[str, InputCommand]]]:
    applied: list[tuple[str, InputCommand]] = []
    arb = InputArbiter(apply=lambda u, c: applied.append((u, c)), clock=lambda: 0.0)
    arb.add(Source("joy", ("left", "right"), priority=10, timeout=0.5))
    arb.add(Source("keys", ("left",), priority=0, timeout=0.5))
    arb.add(Source("net", ("left",), priority=0, timeout=0.5))
    return arb, applied


def test_higher_priority_wins_and_lower_takes_over_when_it_goes_stale() -> None:
    arb, applied = arbiter()
    arb.submit("keys", Twist(0.1, 0), 0.0)
    arb.submit("joy", Twist(0.5, 0), 0.1)
    arb.submit("keys", Twist(0.2, 0), 0.2)  # lower priority: ignored while joy is fresh
    assert applied == [("left", Twist(0.1, 0)), ("left", Twist(0.5, 0)), ("right", Twist(0.5, 0))]
    arb.submit("keys", Twist(0.2, 0), 0.55)
    arb.poll(0.6)  # joy silent for 0.5 s: keys (fresh) takes over left, right stops
    assert applied[-2:] == [("left", Twist(0.2, 0)), ("right", ZERO)]


def test_equal_priority_most_recent_wins() -> None:
    arb, applied = arbiter()
    arb.submit("keys", Twist(0.1, 0), 0.0)
    arb.submit("net", VelocityYX(5, 0), 0.1)
    assert applied[-1] == ("left", VelocityYX(5, 0))


def test_silence_longer_than_the_timeout_means_zero() -> None:
    arb, applied = arbiter()
    arb.submit("keys", Twist(0.1, 0), 1.0)
    assert arb.next_deadline() == 1.5
    arb.poll(1.49)
    assert applied == [("left", Twist(0.1, 0))]
    arb.poll(1.5)
    assert applied[-1] == ("left", ZERO)
    arb.poll(2.0)  # zero is applied once, not every tick
    assert len(applied) == 2


def test_release_means_zero_at_once() -> None:
    arb, applied = arbiter()
    arb.submit("joy", Twist(0.3, 0.1), 0.0)
    arb.submit("joy", None, 0.05)
    assert applied[-2:] == [("left", ZERO), ("right", ZERO)]


def test_repeating_the_same_command_applies_it_once() -> None:
    arb, applied = arbiter()
    for i in range(10):
        arb.submit("joy", Twist(0.3, 0), i * 0.05)
    assert len(applied) == 2  # left and right, once each
