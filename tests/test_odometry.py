"""Dead reckoning from pulse counts: formulas, wrap-around, and agreement with the twist."""

from __future__ import annotations

import math

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.kinematics import Geometry
from abh3_supervisor.core.odometry import PulseOdometry, yaw_quaternion
from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.core import StatusEvent
from abh3_supervisor.simulator.drive import PULSES_PER_REV
from tests.support.rig import Rig, present

G = Geometry(pulses_per_rev=1000)  # 1 pulse = 0.1 / 10 · 0.1 · π / 1000 m


def test_straight_line_and_turn_in_place() -> None:
    odo = PulseOdometry(G)
    odo.update(0, 0)
    pose = odo.update(1000, 1000)  # one motor revolution on both wheels
    assert (pose.x, pose.y, pose.yaw) == pytest.approx((G.metres_per_motor_rev, 0, 0))
    quarter = math.pi / 2 * G.width / 2 / odo.metres_per_pulse  # each wheel's pulses
    odo = PulseOdometry(G)
    odo.update(0, 0)
    pose = odo.update(round(-quarter), round(quarter))  # right wheel forward: counter-clockwise
    assert pose.yaw == pytest.approx(math.pi / 2, rel=1e-3)
    assert math.hypot(pose.x, pose.y) == pytest.approx(0, abs=1e-9)


def test_counter_wrap_is_a_small_step() -> None:
    odo = PulseOdometry(G)
    odo.update(2**31 - 10, -(2**31) + 5)
    pose = odo.update(-(2**31) + 10, 2**31 - 5)  # +20 on A across the top, −10 on B
    assert pose.x == pytest.approx(5 * odo.metres_per_pulse)


def test_needs_pulses_per_rev() -> None:
    with pytest.raises(ValueError, match="pulses_per_rev"):
        PulseOdometry(Geometry())


def test_quaternion_of_a_yaw() -> None:
    x, y, z, w = yaw_quaternion(math.pi / 2)
    assert x == y == 0 and z * z + w * w == pytest.approx(1)
    assert 2 * math.atan2(z, w) == pytest.approx(math.pi / 2)


def test_odometry_follows_a_commanded_twist_on_the_simulated_drive() -> None:
    """Drive an arc for 4 s: the pulses integrate to what the twist says, signs included."""
    cfg = parse_config(
        "buses: {b: {interface: virtual, channel: t, simulate: true}}\n"
        "units: [{name: u, broadcast: {mask: 0x10, rate_hz: 50},\n"
        f"  geometry: {{pulses_per_rev: {PULSES_PER_REV}}},\n"
        "  startup: ['SERVO ON ON', 'START ON ON']}]\n",
        "c.yaml",
    )
    rig = Rig(cfg)
    for text in cfg.units["u"].startup:
        rig.sup.apply_text("u", text)
    odo = PulseOdometry(cfg.units["u"].geometry)

    def on_event(event: object) -> None:
        if isinstance(event, StatusEvent) and isinstance(event.record, frames.Brd4):
            odo.update(event.record.pulse_a, event.record.pulse_b)

    rig.sup.subscribe(on_event)
    rig.run(0.5)  # first reading: the origin
    rig.sup.set_twist("u", 0.1, 0.2, source=present(rig.sup, "u"))
    rig.run(1.0)  # ramp
    start = odo.pose
    rig.run(4.0)
    pose = odo.pose
    assert pose.yaw - start.yaw == pytest.approx(0.8, rel=0.02)  # 0.2 rad/s · 4 s, CCW
    chord = math.hypot(pose.x - start.x, pose.y - start.y)
    radius = 0.1 / 0.2
    assert chord == pytest.approx(2 * radius * math.sin(0.4), rel=0.02)
