"""Input arbitration on a fake clock: priority, recency, staleness and release mean zero."""

from __future__ import annotations

import asyncio

import pytest

from abh3_supervisor.config import ControlMode, parse_config
from abh3_supervisor.core.commands import CurrentCommand
from abh3_supervisor.core.inputs import (
    ZERO,
    InputArbiter,
    InputCommand,
    InputSource,
    Twist,
    VelocityYX,
)
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.scheduler.core import StatusEvent
from tests.support.rig import TWO_UNITS, Rig


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
    arb = rig.sup.arbiter
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


class Holder(InputSource):
    """Keeps the feed so the test can call it from another thread, as a network source."""

    feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        pass


@pytest.mark.wallclock
def test_feed_runs_commands_inputs_and_status_requests_from_another_thread() -> None:
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    source = Holder("net", ("right",))
    host.add_source(source)

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host) as rt:
            sup = rt.supervisor
            answered = asyncio.Event()
            sup.subscribe(
                lambda e: (
                    answered.set()
                    if isinstance(e, StatusEvent) and e.unit == "right" and e.packet == 6
                    else None
                )
            )
            feed = source.feed
            assert feed is not None
            # the seed's inp_service answers, waited for in a thread as a DDS reader does
            assert await asyncio.to_thread(feed.command("SERVO ON ON").result, 5) == ""
            assert await asyncio.to_thread(feed.command("FOO").result, 5) == "Invalid Command."
            right, left = sup.units["right"].layout, sup.units["left"].layout  # 2023, 2021
            assert sup.units["right"].inputs & right.servo.both == right.servo.both
            await asyncio.to_thread(feed.inputs, 0xFFFFFFFF, right.start.both)  # inp_data
            await asyncio.to_thread(feed.request_status, 6)  # brd_num, outside the mask
            # both were queued on the loop before the thread returned: applied by now
            assert sup.units["right"].inputs & right.start.both == right.start.both
            assert sup.units["left"].inputs & left.servo.both == 0  # the source's units only
            await asyncio.wait_for(answered.wait(), 5)
            host.stop_inputs()
            feed.inputs(0, right.servo.both)  # after the inputs stopped: ignored
            assert await asyncio.to_thread(feed.command("SERVO OFF OFF").result, 5) == (
                "Invalid Command."
            )
            await asyncio.sleep(0)  # the queued call runs, and does nothing
            assert sup.units["right"].inputs & right.servo.both == right.servo.both

    asyncio.run(scenario())


@pytest.mark.wallclock
def test_a_vel_through_a_plugins_feed_is_that_sources_motion_and_lapses_with_it() -> None:
    """inp_service's VEL is the bridge source's motion like vel_cmd: fresh for the
    source's timeout, then zero — never a static setpoint nobody owns."""
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    source = Holder("net", ("right",), timeout=0.1)
    host.add_source(source)

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host) as rt:
            sup, feed = rt.supervisor, source.feed
            assert feed is not None
            for text in ("SERVO ON ON", "START ON ON"):  # a robot moves only switched on
                assert await sup.command("right", text) == ""
            assert await asyncio.to_thread(feed.command("VEL 100 -50").result, 5) == ""
            assert sup.units["right"].setpoint.ay == 100.0  # held by the source now
            loop = asyncio.get_running_loop()
            start = loop.time()
            while sup.units["right"].setpoint.ay != 0.0:  # the arbiter's own timer zeroes it
                assert loop.time() - start < 2.0, "the VEL outlived its source's timeout"
                await asyncio.sleep(0.01)

    asyncio.run(scenario())
