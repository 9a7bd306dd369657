"""Input arbitration on a fake clock: priority, recency, staleness and release mean zero."""

from __future__ import annotations

from abh3_supervisor.commands import CurrentCommand
from abh3_supervisor.config import ControlMode
from abh3_supervisor.inputs import (
    ZERO,
    InputArbiter,
    InputCommand,
    InputFeed,
    InputSource,
    Twist,
    VelocityYX,
)
from tests.conftest import Rig


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


def test_silence_zeroes_a_unit_in_current_mode_too(rig: Rig) -> None:
    from abh3_supervisor.plugin_host import _apply

    arb = InputArbiter(apply=lambda u, c: _apply(rig.sup, u, c), clock=rig.timeline.clock)
    arb.add(Source("net", ("left",), priority=0, timeout=0.5))
    assert rig.sup.apply_text("left", "TORQUE ON ON") == ""
    arb.submit("net", CurrentCommand(12.5, -3.0), 0.0)
    assert (rig.sup.units["left"].setpoint.ay, rig.sup.units["left"].setpoint.kind) == (
        12.5,
        ControlMode.CURRENT,
    )
    arb.poll(0.5)  # silent for its timeout: zero current, still in current mode
    setpoint = rig.sup.units["left"].setpoint
    assert (setpoint.ay, setpoint.bx, setpoint.kind) == (0.0, 0.0, ControlMode.CURRENT)


def test_repeating_the_same_command_applies_it_once() -> None:
    arb, applied = arbiter()
    for i in range(10):
        arb.submit("joy", Twist(0.3, 0), i * 0.05)
    assert len(applied) == 2  # left and right, once each
