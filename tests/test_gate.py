"""The motion gate (core/gate.py): every edge of issue 29 that the gate closes, judged by
what the simulated *drive* was told, on a fake clock."""

from __future__ import annotations

import asyncio
import math

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import VerifyMode
from abh3_supervisor.core.commands import RESPONSE_INVALID, VelocityCommand
from abh3_supervisor.core.gate import ESTOP_POWER_OFF_S, MotionGate
from abh3_supervisor.core.inputs import InputSource, Twist
from abh3_supervisor.core.verify import Row, State, Verification
from abh3_supervisor.errors import CommandError
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.protocol import scaling
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.support.rig import TWO_UNITS, Rig, set_velocity


class Source(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


def told(rig: Rig, unit: str = "left") -> float:
    """The AY velocity the simulated drive was last told [min⁻¹]."""
    return scaling.VELOCITY.to_physical(rig.drive(unit).cmd_raw[0])


def switches(rig: Rig, unit: str = "left") -> int:
    """SERVO, START and brake release as the drive was last told them."""
    lay = rig.sup.units[unit].layout
    inputs: int = rig.drive(unit).inputs
    return inputs & (lay.servo.both | lay.start.both | lay.brake_release)


def running(rig: Rig, unit: str = "left") -> None:
    for text in ("SERVO ON ON", "START ON ON", "BRAKE ON ON"):
        assert rig.sup.apply_text(unit, text) == "", text


def client(rig: Rig, name: str = "client", unit: str = "left") -> str:
    rig.sup.arbiter.add(Source(name, (unit,), priority=0, timeout=math.inf))
    return name


def test_after_a_cleared_estop_the_same_standing_value_given_again_moves_the_drive(
    rig: Rig,
) -> None:
    """The e-stop voids the arbitration: after the clear nothing moves until a command given
    after it, and the same value as before is such a command — obeyed, not "no change"."""
    running(rig)
    name = client(rig)
    rig.sup.arbiter.submit(name, VelocityCommand(400, 0), rig.timeline.now, standing=True)
    rig.run(0.5)
    assert told(rig) == 400.0
    rig.sup.emergency_stop("test")
    rig.run(0.2)
    rig.sup.clear_emergency_stop()
    rig.run(0.2)
    assert told(rig) == 0.0  # nothing moves after the clear by itself
    for text in ("SERVO ON ON", "START ON ON"):  # the e-stop powered the unit off
        assert rig.sup.apply_text("left", text) == ""
    rig.run(0.2)
    assert told(rig) == 0.0
    rig.sup.arbiter.submit(name, VelocityCommand(400, 0), rig.timeline.now, standing=True)
    rig.run(0.3)
    assert told(rig) == 400.0
    assert rig.sup.units["left"].setpoint.owner == name


def test_a_stream_heard_before_a_long_estop_is_not_back_after_the_clear(rig: Rig) -> None:
    running(rig)
    rig.sup.arbiter.add(Source("stick", ("left",), priority=0, timeout=10.0))
    rig.sup.arbiter.submit("stick", VelocityCommand(250, 0), rig.timeline.now)
    rig.run(0.3)
    rig.sup.emergency_stop("test")
    rig.run(0.8)
    rig.sup.clear_emergency_stop()
    running(rig)
    rig.run(0.5)
    assert told(rig) == 0.0 and rig.sup.units["left"].setpoint.ay == 0.0


def test_estop_is_stop_category_1_zero_and_start_off_at_once_then_servo_and_brake(
    rig: Rig,
) -> None:
    running(rig)
    set_velocity(rig.sup, "left", 300, 0)
    rig.run(1.0)
    lay = rig.sup.units["left"].layout
    rig.sup.emergency_stop("test")
    frames_before = len(rig.timeline.frames)
    rig.run(0.03)  # the next frame: zero, START off, the servo still on (the drive's ramp)
    assert told(rig) == 0.0 and not rig.drive("left").inputs & lay.start.both
    assert rig.drive("left").inputs & lay.servo.both
    assert len(rig.timeline.frames) > frames_before
    rig.run(ESTOP_POWER_OFF_S)  # the drive reported it stopped, or the bound passed
    assert switches(rig) == 0
    with pytest.raises(CommandError, match="emergency stop is latched"):
        rig.sup.set_inputs("left", lay.servo.both, lay.servo.both)
    assert rig.sup.apply_text("left", "BRAKE ON ON") != ""


def test_a_parameter_write_locks_servo_off_until_it_ends(rig: Rig) -> None:
    """A lock, not a check before the write: SERVO ON from anyone is refused while the
    write is in flight, and the drive sees the safe word throughout."""
    lay = rig.sup.units["left"].layout
    assert rig.sup.apply_text("left", "START ON ON") == ""
    with rig.sup.param_write("left"):
        rig.run(0.1)
        assert switches(rig) == 0
        assert rig.sup.apply_text("left", "SERVO ON ON") == RESPONSE_INVALID
        with pytest.raises(CommandError, match="parameter write is in flight"):
            rig.sup.set_inputs("left", lay.servo.both, lay.servo.both)
        with pytest.raises(CommandError, match="parameter write is in flight"):
            set_velocity(rig.sup, "left", 10, 0)
        rig.run(0.1)
        assert switches(rig) == 0
    assert rig.sup.apply_text("left", "SERVO ON ON") == ""  # the write ended
    rig.run(0.1)
    assert rig.drive("left").inputs & lay.servo.both
    assert not rig.drive("left").inputs & lay.start.both  # consumed by the lock


def test_the_lock_is_refused_while_this_supervisor_commands_servo_on(rig: Rig) -> None:
    running(rig)
    with pytest.raises(CommandError, match="commands its servo ON"), rig.sup.param_write("left"):
        pass
    assert not rig.sup.gate.written("left")


def test_a_held_unit_sends_the_safe_word_brake_included_and_refuses_vel(rig: Rig) -> None:
    running(rig)
    set_velocity(rig.sup, "left", 200, 0)
    rig.run(0.5)
    assert told(rig) == 200.0 and switches(rig)
    row = Row(0x4117, "750 ms", "drive_timeout_ms: 500", False)
    rig.sup.units["left"].verify = Verification(State.MISMATCH, VerifyMode.REFUSE, rows=(row,))
    rig.sup.restrict("left")
    rig.run(0.1)
    assert told(rig) == 0.0 and switches(rig) == 0  # the brake release too
    assert rig.sup.apply_text("left", "VEL 100 50") == RESPONSE_INVALID
    with pytest.raises(CommandError, match="held at its idle word"):
        rig.sup.refuse_motion("left")
    # verified again: nothing comes back by itself
    rig.sup.units["left"].verify = Verification(State.OK, VerifyMode.REFUSE)
    rig.sup._push(rig.sup.units["left"])
    rig.run(0.2)
    assert told(rig) == 0.0 and switches(rig) == 0


def test_the_gate_masks_a_request_stored_past_it(rig: Rig) -> None:
    """By construction: even state set behind the Supervisor's back cannot reach the wire
    while the gate forbids it."""
    unit = rig.sup.units["left"]
    lay = unit.layout
    row = Row(0x4117, "750 ms", "drive_timeout_ms: 500", False)
    rig.sup.units["left"].verify = Verification(State.MISMATCH, VerifyMode.REFUSE, rows=(row,))
    unit.inputs |= lay.servo.both | lay.start.both | lay.brake_release
    rig.sup._push(unit)
    rig.run(0.1)
    assert switches(rig) == 0


def test_a_setpoint_whose_owner_lost_the_unit_is_zero_on_the_wire() -> None:
    config = parse_config(TWO_UNITS, "two.yaml")
    unit_state = Rig(config).sup.units["left"]
    gate = MotionGate()
    from abh3_supervisor.core.state import Setpoint

    unit_state.identified = unit_state.cfg.protocol  # its replies showed its generation
    unit_state.setpoint = Setpoint(300, 20, owner="someone")
    assert (gate.word(unit_state, owned=True).ay, gate.word(unit_state, owned=False).ay) == (300, 0)


def test_the_public_api_owns_its_motion_only_while_it_repeats_it() -> None:
    """A VEL given to Supervisor.apply_text (its programmatic entry) is the streamed
    source api:<unit>'s: silence is zero."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    del rig.sup.arbiter.sources["api:left"]  # the rig's own standing one: the real default
    running(rig)
    assert rig.sup.apply_text("left", "VEL 300 0") == ""
    rig.run(0.3)
    assert told(rig) == 300.0
    rig.run(0.5)
    assert told(rig) == 0.0
    assert rig.sup.units["left"].setpoint.owner is None


def test_a_twist_refused_in_the_arbitration_zeroes_the_unit_and_a_repeat_is_applied(
    rig: Rig,
) -> None:
    running(rig)
    name = client(rig)
    rig.sup.arbiter.submit(name, Twist(0.2, 0.0), rig.timeline.now)
    rig.run(0.2)
    assert told(rig) != 0.0
    rig.sup.emergency_stop("test")
    rig.sup.arbiter.submit(name, Twist(0.2, 0.0), rig.timeline.now)  # refused: latched
    rig.run(0.2)
    assert told(rig) == 0.0
    rig.sup.clear_emergency_stop()
    running(rig)
    rig.sup.arbiter.submit(name, Twist(0.2, 0.0), rig.timeline.now)  # the same, after
    rig.run(0.2)
    assert told(rig) != 0.0


def test_the_runtime_sends_the_estop_frame_at_once_without_plugins() -> None:
    """Every runtime has the arbitration and the e-stop's immediate frames, plugins or not:
    both stop frames are handed to the bus within the call, not at the next period."""
    text = TWO_UNITS.replace("command_rate_hz: 50", "command_rate_hz: 5").replace(
        "channel: t", "channel: gate-now"
    )
    config = parse_config(text, "slow.yaml")

    async def scenario() -> tuple[float, float]:
        async with Runtime(config) as rt:
            sup = rt.supervisor
            await sup.wait_exchange("left", sup.clock(), 2.0)  # the next is ~0.2 s away
            sent = rt.pumps["b"].frames_sent
            t = sup.clock()
            sup.emergency_stop("test")
            return rt.pumps["b"].frames_sent - sent, sup.clock() - t

    extra, took = asyncio.run(scenario())
    assert extra == 2  # both commanded units' stop frames, at once
    assert took < 0.01


def test_an_error_reset_admitted_on_a_held_unit_is_sent(rig: Rig) -> None:
    """What a restricted unit is answered OK for goes out: an error reset moves nothing."""
    lay = rig.sup.units["left"].layout
    row = Row(0x4117, "750 ms", "drive_timeout_ms: 500", False)
    rig.sup.units["left"].verify = Verification(State.MISMATCH, VerifyMode.REFUSE, rows=(row,))
    rig.sup.restrict("left")
    assert rig.sup.apply_text("left", "RESET ON ON") == ""
    rig.run(0.1)
    assert rig.drive("left").inputs & lay.error_reset and switches(rig) == 0
