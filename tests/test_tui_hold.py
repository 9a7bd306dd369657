"""A held arrow key on a fake clock: the terminal's key-repeat delay never stops the robot,
and the key's release (no more repeats) stops it within a bound (issue 29, item 5).

The terminal is simulated as measured: the press, the first auto-repeat 0.6 s later, then
one every 0.033 s. The TUI's side is :class:`HeldKey` ticked as the app ticks it; what it
sends goes into the service's arbitration (its client timeout), whose setpoint is checked
every 5 ms.
"""

from __future__ import annotations

import itertools

import pytest

from abh3_supervisor.clients.tui.hold import (
    FIRST_REPEAT_S,
    REPEAT_GAP_S,
    RESEND_S,
    TICK_S,
    Drive,
    HeldKey,
)
from abh3_supervisor.core.inputs import ZERO, InputArbiter, InputCommand, InputSource
from abh3_supervisor.core.inputs import Twist as Motion
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.service.server import CLIENT_TIMEOUT_S

UP = Drive(("left",), 0.2, 0.0)
STEP = 0.005


class Client(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


def repeats(first: float, until: float, every: float = 0.033) -> list[float]:
    """The key events of a key pressed at 0 and held: the press, then auto-repeats."""
    times, t = [0.0], first
    while t <= until:
        times.append(round(t, 6))
        t += every
    return times


def run(keys: list[float], end: float) -> list[tuple[float, InputCommand]]:
    """Key events and the app's ticks in time order; what the service applies, when."""
    applied: list[tuple[float, InputCommand]] = []
    now = [0.0]
    arb = InputArbiter(apply=lambda _u, c: applied.append((now[0], c)), clock=lambda: now[0])
    arb.add(Client("tui", ("left",), priority=0, timeout=CLIENT_TIMEOUT_S))
    held = HeldKey()
    pending = sorted(keys)
    ticks = 0
    for i in range(round(end / STEP) + 1):
        now[0] = t = round(i * STEP, 6)
        while pending and pending[0] <= t:
            pending.pop(0)
            if held.press(UP, t):  # the app sends a new drive at once
                arb.submit("tui", Motion(UP.linear, UP.angular), t)
        if t >= ticks * TICK_S:  # the app's interval timer
            ticks += 1
            due = held.tick(t)
            if due is not None:
                drive, again = due
                motion = Motion(drive.linear, drive.angular) if again else Motion(0.0, 0.0)
                arb.submit("tui", motion, t)
        arb.poll(t)
    return applied


def stopped(command: InputCommand) -> bool:
    return command == ZERO or command == Motion(0.0, 0.0)


@pytest.mark.parametrize("first", [0.5, 0.6, 0.66, 0.7])
def test_the_repeat_delay_never_stops_a_held_key_and_the_release_stops_it(first: float) -> None:
    keys = repeats(first, until=2.0)
    applied = run(keys, end=3.0)
    assert applied[0] == (0.0, Motion(0.2, 0.0))  # the press drives at once
    moving_until = next(t for t, c in applied if stopped(c))
    assert moving_until > keys[-1], applied  # never zero while the key repeats
    assert moving_until <= keys[-1] + REPEAT_GAP_S + TICK_S  # released: zero soon
    assert all(stopped(c) for t, c in applied if t >= moving_until)  # and it stays zero


def test_the_measured_case_382_to_0_at_049_s_no_longer_happens() -> None:
    """The measurement: the setpoint went to zero at +0.49 s and back at +0.61 s."""
    applied = run(repeats(0.61, until=1.5), end=2.0)
    assert [c for t, c in applied if t < 1.5] == [Motion(0.2, 0.0)]


def test_a_tap_drives_for_the_first_repeat_window_then_stops() -> None:
    applied = run([0.0], end=2.0)
    assert applied[0] == (0.0, Motion(0.2, 0.0))
    stop = next(t for t, c in applied if stopped(c))
    assert FIRST_REPEAT_S <= stop <= FIRST_REPEAT_S + TICK_S
    assert FIRST_REPEAT_S + TICK_S < 1.0  # a tap is still a short nudge


def test_silence_still_means_zero_within_the_services_timeout() -> None:
    """The TUI re-sends well inside the client timeout; if it stops (hung, killed), the
    service's own timeout zeroes the twist."""
    assert RESEND_S + TICK_S < CLIENT_TIMEOUT_S
    held = HeldKey()
    assert held.press(UP, 0.0)
    sends = [t for t in (i * TICK_S for i in range(1, 12)) if held.tick(t) is not None]
    assert sends and all(b - a <= RESEND_S + TICK_S for a, b in itertools.pairwise([0.0, *sends]))
    applied: list[InputCommand] = []
    arb = InputArbiter(apply=lambda _u, c: applied.append(c), clock=lambda: 0.0)
    arb.add(Client("tui", ("left",), priority=0, timeout=CLIENT_TIMEOUT_S))
    arb.submit("tui", Motion(0.2, 0.0), sends[-1])  # then the TUI falls silent
    arb.poll(sends[-1] + CLIENT_TIMEOUT_S)
    assert applied == [Motion(0.2, 0.0), ZERO]


def test_another_arrow_is_sent_at_once_and_space_or_the_estop_ends_the_hold() -> None:
    held = HeldKey()
    assert held.press(UP, 0.0)
    assert not held.press(UP, 0.6)  # a repeat: kept going, not sent again
    left = Drive(("left",), 0.0, 0.5)
    assert held.press(left, 0.62)  # another key: sent now, its own repeat delay waited
    assert held.tick(0.62 + REPEAT_GAP_S) == (left, True)  # not taken as released yet
    held.stop()
    assert held.drive is None and held.tick(5.0) is None  # nothing more is sent
