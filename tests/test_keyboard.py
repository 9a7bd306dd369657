"""Keyboard teleop: the key map, and a real terminal (a pseudo-terminal) end to end."""

from __future__ import annotations

import os
import pty
import termios
import threading

import pytest

from abh3_plugins.keyboard import KeyboardSource, Teleop
from abh3_supervisor.plugin_host import terminal


def test_teleop_twist_keyboard_layout() -> None:
    t = Teleop(speed=0.5, turn=1.0)
    assert t.key("i") == (0.5, 0.0)
    assert t.key(",") == (-0.5, 0.0)
    assert t.key("j") == (0.0, 1.0)
    assert t.key("l") == (0.0, -1.0)
    assert t.key("u") == (0.5, 1.0)
    assert t.key(" ") == (0.0, 0.0) and t.key("k") == (0.0, 0.0)
    assert t.key("q") is None and t.key("i") == pytest.approx((0.55, 0.0))
    assert t.key("?") is None


class Feed:
    def __init__(self, want: int) -> None:
        self.sent: list[tuple[float, float] | None] = []
        self.want = want
        self.stops = 0
        self.done = threading.Event()

    def twist(self, linear_x: float, angular_z: float) -> None:
        self.sent.append((linear_x, angular_z))
        if len(self.sent) >= self.want:
            self.done.set()

    def velocity_yx(self, y: float, x: float) -> None:
        raise AssertionError

    velocity = current = velocity_ab = velocity_yx

    def release(self) -> None:
        self.sent.append(None)

    def emergency_stop(self) -> None:
        self.sent.append(None)
        self.stops += 1
        if len(self.sent) >= self.want:
            self.done.set()


@pytest.mark.wallclock
def test_keys_typed_in_a_terminal_drive_and_the_terminal_is_restored() -> None:
    master, slave = pty.openpty()
    stream = os.fdopen(slave, "r")
    before = termios.tcgetattr(slave)
    source = KeyboardSource(("left",), 0, 0.6, Teleop(0.2, 0.5), stream=stream)
    feed = Feed(want=3)
    source.start(feed)  # type: ignore[arg-type]
    try:
        assert not termios.tcgetattr(slave)[3] & termios.ECHO  # cbreak: no echo
        os.write(master, b"ijk")
        assert feed.done.wait(5)
    finally:
        source.stop()
    assert feed.sent == [(0.2, 0.0), (0.0, 0.5), (0.0, 0.0)]
    assert termios.tcgetattr(slave) == before
    stream.close()
    os.close(master)


def test_ctrl_e_typed_in_its_terminal_is_the_estop_and_sends_no_twist() -> None:
    master, slave = pty.openpty()
    stream = os.fdopen(slave, "r")
    source = KeyboardSource(("left",), 0, 0.6, Teleop(0.2, 0.5), stream=stream)
    feed = Feed(want=3)
    source.start(feed)  # type: ignore[arg-type]
    try:
        os.write(master, b"i\x05i")
        assert feed.done.wait(5)
    finally:
        source.stop()
    assert feed.sent == [(0.2, 0.0), None, (0.2, 0.0)] and feed.stops == 1
    stream.close()
    os.close(master)


def test_under_a_terminal_owner_it_reads_nothing_and_takes_the_keys_it_is_given() -> None:
    terminal.claim("the TUI")
    try:
        source = KeyboardSource(("left",), 0, 0.6, Teleop(0.2, 0.5), stream=object())
        feed = Feed(want=2)
        source.start(feed)  # type: ignore[arg-type]  # a stream it touched would raise
        keys = source.key_map({"q", "e", " "})  # the owner's own keys
        assert "q" not in keys and "e" not in keys and " " not in keys
        assert keys["Q"] == "all speeds ×1.1" and keys["C"] == "angular speed ×1.1"
        for key in ("i", "Q", "i", "x"):  # x: linear ×0.9 sends nothing
            source.press(key)
        source.stop()
        source.press("i")  # after stop: ignored
    finally:
        terminal.release()
    assert feed.sent == [(0.2, 0.0), pytest.approx((0.22, 0.0))]
