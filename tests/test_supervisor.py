"""The Supervisor API on a fake clock against simulated drives."""

from __future__ import annotations

import asyncio
import math

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.kinematics import twist_to_yx
from abh3_supervisor.core.supervisor import FlagChange, Notice
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.scheduler.core import HealthEvent
from tests.support.rig import (
    TWO_UNITS,
    Rig,
    present,
    set_current,
    set_twist,
    set_velocity,
    set_velocity_ab,
    set_velocity_yx,
)
from tests.support.wire_monitor import WireMonitor


def last_command(rig: Rig, unit: str) -> frames.Dp0Command:
    abh3 = rig.config.units[unit].abh3_id
    frame = [f for f in rig.timeline.frames if f.arbitration_id == ids.dp0_command_id(abh3, 2)][-1]
    cmd = frames.decode_dp0_command(frame.data, rig.config.units[unit].protocol)
    assert isinstance(cmd, frames.Dp0Command)
    return cmd


def start(rig: Rig, *units: str) -> None:
    for unit in units:
        assert rig.sup.apply_text(unit, "SERVO ON ON") == ""
        assert rig.sup.apply_text(unit, "START ON ON") == ""


def test_velocity_in_any_model_reaches_the_drive_in_its_own(rig: Rig) -> None:
    start(rig, "left", "right")
    set_velocity_ab(
        rig.sup, "left", 120, 80, source=rig.own("left")
    )  # left is a travel-model drive: sends Y 100, X 20
    set_velocity_yx(
        rig.sup, "right", 100, 20, source=rig.own("right")
    )  # right is a motor-model drive: sends A 120, B 80
    rig.run(1.0)
    assert (last_command(rig, "left").cmd_ay, last_command(rig, "left").cmd_bx) == (100.0, 20.0)
    assert (last_command(rig, "right").cmd_ay, last_command(rig, "right").cmd_bx) == (120.0, 80.0)
    for unit in ("left", "right"):
        fb = rig.sup.units[unit].feedback
        assert fb is not None
        assert (fb.vel_a, fb.vel_b, fb.vel_y, fb.vel_x) == (120.0, 80.0, 100.0, 20.0)


def test_twist_goes_through_the_unit_geometry(rig: Rig) -> None:
    start(rig, "left")
    result = set_twist(rig.sup, "left", 0.05, 0.1, source=present(rig.sup, "left"))
    y, x = twist_to_yx(0.05, 0.1, rig.config.units["left"].geometry)
    assert (result.ay, result.bx) == pytest.approx((y, x))


def test_clamping_scales_both_axes_and_is_reported() -> None:
    rig = Rig(
        parse_config(
            TWO_UNITS.replace("name: left,", "name: left, limits: {velocity: 100},"), "l.yaml"
        )
    )
    result = set_velocity(rig.sup, "left", 400, -200, source=present(rig.sup, "left"))
    assert (result.ay, result.bx, result.clamped) == (100.0, -50.0, True)
    notices = [e for e in rig.events if isinstance(e, Notice)]
    assert notices[-1].message == "clamped: VEL 400 -200 → 100 -50 (limits.velocity 100)"


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_rejected(rig: Rig, bad: float) -> None:
    with pytest.raises(CommandError, match="not a finite number"):
        set_velocity(rig.sup, "left", bad, 0, source=present(rig.sup, "left"))
    with pytest.raises(CommandError):
        set_twist(rig.sup, "left", 0, bad, source=present(rig.sup, "left"))


def test_command_language_responses(rig: Rig) -> None:
    assert rig.sup.apply_text("left", "SERVO ON ON") == ""
    assert rig.sup.apply_text("left", "FOO") == "Invalid Command."
    assert rig.sup.apply_text("left", "SERVO ON") == "Invalid Command."
    servo = flags.LAYOUT_2021.servo.both
    assert rig.sup.units["left"].inputs & servo == servo
    with pytest.raises(CommandError, match="no unit named 'middle'"):
        rig.sup.apply_text("middle", "SERVO ON ON")


def test_input_data_and_mask_like_the_seed_topic(rig: Rig) -> None:
    before = rig.sup.units["left"].inputs
    rig.sup.set_inputs("left", 0xFFFFFFFF, flags.LAYOUT_2021.servo.ay)
    assert rig.sup.units["left"].inputs == before | flags.LAYOUT_2021.servo.ay


def test_current_needs_torque_mode_and_mode_change_zeroes_the_command(rig: Rig) -> None:
    start(rig, "left")
    set_velocity(rig.sup, "left", 100, 0, source=present(rig.sup, "left"))
    with pytest.raises(CommandError, match="velocity mode; a current command needs TORQUE ON ON"):
        set_current(rig.sup, "left", 10, 10, source=present(rig.sup, "left"))
    assert rig.sup.apply_text("left", "TORQUE ON ON") == ""
    assert (rig.sup.units["left"].setpoint.ay, rig.sup.units["left"].setpoint.bx) == (0, 0)
    set_current(rig.sup, "left", 12.5, -3, source=present(rig.sup, "left"))
    rig.run(0.1)
    cmd = last_command(rig, "left")
    assert (cmd.cmd_ay, cmd.cmd_bx, cmd.ay_is_current) == (12.5, -3.0, True)
    assert rig.sup.apply_text("left", "VEL 10 10") == "Invalid Command."


def test_emergency_stop_latches_until_cleared(rig: Rig, wire: WireMonitor) -> None:
    start(rig, "left", "right")
    set_velocity(rig.sup, "left", 300, 0, source=present(rig.sup, "left"))
    set_velocity(rig.sup, "right", 300, 300, source=present(rig.sup, "right"))
    rig.run(0.5)
    rig.sup.emergency_stop()
    wire.estop()
    rig.run(0.1)
    for unit in ("left", "right"):
        cmd = last_command(rig, unit)
        assert (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0)
        lay = rig.sup.units[unit].layout
        assert not cmd.inputs & lay.start.both and cmd.inputs & lay.servo.both
    with pytest.raises(CommandError, match="emergency stop is latched"):
        set_velocity(rig.sup, "left", 10, 0, source=present(rig.sup, "left"))
    assert rig.sup.apply_text("left", "START ON ON") == "Packet Error: 3"
    set_velocity(rig.sup, "left", 0, 0, source=present(rig.sup, "left"))  # zero is always allowed
    rig.run(0.1)
    wire.clear()
    rig.sup.clear_emergency_stop()
    # the e-stop switched SERVO off too: both are given anew before motion is taken
    with pytest.raises(CommandError, match="SERVO A, SERVO B, START A, START B not switched"):
        set_velocity(rig.sup, "left", 10, 0, source=present(rig.sup, "left"))
    for text in ("SERVO ON ON", "START ON ON"):
        assert rig.sup.apply_text("left", text) == ""
    set_velocity(rig.sup, "left", 10, 0, source=present(rig.sup, "left"))


def test_an_offline_unit_has_its_command_zeroed(rig: Rig) -> None:
    start(rig, "left")
    set_velocity(rig.sup, "left", 300, 0, source=present(rig.sup, "left"))
    rig.run(0.5)
    rig.drive("left").silent = True
    rig.run(1.5)
    assert any(isinstance(e, HealthEvent) and not e.online for e in rig.events)
    assert (rig.sup.units["left"].setpoint.ay, rig.sup.units["left"].online) == (0.0, False)
    rig.drive("left").silent = False
    rig.run(1.5)
    assert last_command(rig, "left").cmd_ay == 0.0  # not resumed with the stale 300


def test_error_and_alarm_changes_are_events_with_names(rig: Rig) -> None:
    start(rig, "left")
    rig.run(1.0)
    rig.drive("left").inject_error(flags.FAULT.mask("A_OVERCURRENT"))
    rig.run(1.0)
    changes = [
        e
        for e in rig.events
        if isinstance(e, FlagChange) and e.word == "error" and e.unit == "left" and e.set_bits
    ]
    assert [flags.FAULT.names(c.set_bits) for c in changes] == [["A_OVERCURRENT"]]
    assert rig.sup.apply_text("left", "RESET ON ON") == ""
    rig.run(1.0)
    assert rig.sup.units["left"].words["error"] == 0


def test_model_mismatch_is_reported() -> None:
    rig = Rig(parse_config(TWO_UNITS, "t.yaml"))
    rig.drive("left").file_model = rig.config.units["right"].velocity_model  # runs motor
    rig.run(1.0)
    assert any(
        isinstance(e, Notice) and "configuration says velocity_model: travel" in e.message
        for e in rig.events
    )


def test_monitor_units_refuse_commands() -> None:
    rig = Rig(parse_config(TWO_UNITS.replace("name: right,", "name: right, role: monitor,"), "m"))
    with pytest.raises(CommandError, match="role: monitor"):
        set_velocity(rig.sup, "right", 1, 1, source=present(rig.sup, "right"))


@pytest.mark.wallclock
def test_exchange_waiters_resolve_on_the_reply_to_a_later_request(rig: Rig) -> None:
    async def scenario() -> None:
        rig.run(0.1)
        future = rig.sup.expect_exchange("left", rig.timeline.now)
        assert not future.done()
        rig.run(0.05)
        assert future.done() and future.result() is True

    asyncio.run(scenario())


def test_safe_state_is_zero_servo_and_start_off(rig: Rig) -> None:
    start(rig, "left", "right")
    set_velocity(rig.sup, "left", 100, 0, source=present(rig.sup, "left"))
    rig.sup.safe_state()
    rig.run(0.1)
    for unit in ("left", "right"):
        cmd = last_command(rig, unit)
        assert (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0)
        lay = rig.sup.units[unit].layout
        assert not cmd.inputs & (lay.start.both | lay.servo.both)


def test_a_failing_observer_does_not_stop_the_others(rig: Rig) -> None:
    def broken(event: object) -> None:
        raise RuntimeError("observer bug")

    rig.sup.subscribe(broken)
    seen: list[object] = []
    rig.sup.subscribe(seen.append)
    rig.run(0.2)
    assert seen
