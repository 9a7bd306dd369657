"""Joystick mapping and device handling with synthetic events; end to end to the frame."""

from __future__ import annotations

import pytest

from abh3_plugins.joystick import (
    JS_AXIS,
    JS_BUTTON,
    DeviceLost,
    JoystickSource,
    JsEvent,
    Mapping,
)
from abh3_supervisor.core.inputs import Twist
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.protocol.generation import Generation
from tests.support.rig import Rig


class FakeDevice:
    def __init__(self, batches: list[list[JsEvent] | Exception]) -> None:
        self.batches = batches
        self.closed = False

    def read(self, timeout: float) -> list[JsEvent]:
        item = self.batches.pop(0) if self.batches else []
        if isinstance(item, Exception):
            raise item
        return item

    def close(self) -> None:
        self.closed = True


class FakeFeed:
    def __init__(self) -> None:
        self.sent: list[tuple[float, float] | None] = []

    def twist(self, linear_x: float, angular_z: float) -> None:
        self.sent.append((linear_x, angular_z))

    def velocity_yx(self, y: float, x: float) -> None:
        raise AssertionError("the joystick sends twists")

    velocity = current = velocity_ab = velocity_yx

    def release(self) -> None:
        self.sent.append(None)


def axis(n: int, value: int) -> JsEvent:
    return JsEvent(JS_AXIS, n, value)


def button(n: int, pressed: bool) -> JsEvent:
    return JsEvent(JS_BUTTON, n, int(pressed))


def test_seed_mapping_axis_4_travel_axis_0_turn_with_gains() -> None:
    m = Mapping(gain_x=2.0, gain_a=0.5, deadman_button=None, scale=1.0)
    m.feed(axis(4, -32767))  # stick pushed up: the kernel reports negative
    m.feed(axis(0, 16384))  # stick to the right: turn right (negative angular.z)
    lin, ang = m.twist() or (0.0, 0.0)
    assert lin == pytest.approx(2.0) and ang == pytest.approx(-0.25, abs=1e-3)


def test_deadman_and_turbo() -> None:
    m = Mapping(scale=0.5, turbo_scale=1.0)
    m.feed(axis(4, -32767))
    assert m.twist() is None  # deadman (button 4) not held
    m.feed(button(4, True))
    assert m.twist() == pytest.approx((0.5, 0.0))
    m.feed(button(5, True))
    assert m.twist() == pytest.approx((1.0, 0.0))


def test_deadman_release_sends_release_and_device_loss_means_zero_then_reopen() -> None:
    opened: list[FakeDevice] = []
    devices: list[list[list[JsEvent] | Exception]] = [
        [
            [button(4, True), axis(4, -32767)],
            [],
            [button(4, False)],
            [button(4, True)],
            DeviceLost("unplugged"),
        ],
        [[button(4, True), axis(0, -32767)], DeviceLost("unplugged again")],
    ]

    def open_device() -> FakeDevice:
        if not devices:
            source._stop.set()  # no third device: end the run
            raise OSError(19, "No such device")
        opened.append(FakeDevice(devices.pop(0)))
        return opened[-1]

    source = JoystickSource(("left",), 10, 0.5, Mapping(), open_device, retry_s=0.0)
    feed = FakeFeed()
    source.run(feed)
    assert feed.sent == [
        (0.5, 0.0),
        (0.5, 0.0),  # re-sent while held, though the stick did not move
        None,  # deadman released: zero at once
        (0.5, 0.0),
        None,  # device lost: zero at once
        pytest.approx((0.0, 0.5)),  # reopened: fresh state, deadman pressed again
        None,
    ]
    assert all(d.closed for d in opened) and len(opened) == 2


def test_deadman_release_gives_zero_on_the_very_next_command_frame(rig: Rig) -> None:
    arb = rig.sup.arbiter
    source = JoystickSource(("left",), 10, 0.5, Mapping(), lambda: None)
    arb.add(source)
    rig.sup.apply_text("left", "SERVO ON ON")
    rig.sup.apply_text("left", "START ON ON")

    class Feed(FakeFeed):
        def twist(self, linear_x: float, angular_z: float) -> None:
            arb.submit("joystick", Twist(linear_x, angular_z), rig.timeline.now)

        def release(self) -> None:
            arb.submit("joystick", None, rig.timeline.now)

    feed = Feed()
    source.step(FakeDevice([[button(4, True), axis(4, -32767)]]), feed)
    rig.run(0.3)
    released_at = rig.timeline.now
    source.step(FakeDevice([[button(4, False)]]), feed)
    rig.run(0.1)
    cmd_id = ids.dp0_command_id(1, 2)
    after = [f for f in rig.timeline.frames if f.arbitration_id == cmd_id and f.start > released_at]
    before = [
        f for f in rig.timeline.frames if f.arbitration_id == cmd_id and f.start <= released_at
    ]
    moving = frames.decode_dp0_command(before[-1].data, Generation.G2021)
    first = frames.decode_dp0_command(after[0].data, Generation.G2021)
    assert isinstance(moving, frames.Dp0Command) and moving.cmd_ay > 0
    assert isinstance(first, frames.Dp0Command) and (first.cmd_ay, first.cmd_bx) == (0.0, 0.0)
