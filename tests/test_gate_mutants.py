"""The motion gate's mutants that tests/test_gate.py let survive (docs/mutation.md): each
test here fails under the mutation named in its docstring. Judged by what the simulated
drive was told where the wire shows it, on a fake clock."""

from __future__ import annotations

import asyncio

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.commands import RESPONSE_INVALID
from abh3_supervisor.core.gate import MotionGate
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import scaling
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.param_ops import ParamFailed, ParamOps
from tests.conftest import TWO_UNITS, Rig

SPEED_AY_0 = 0x5000
ONE_DRIVE = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: true}}
units:
  - {{name: left, abh3_id: 1, command_rate_hz: 100, broadcast: {{mask: 0x7f, rate_hz: 2}}}}
"""


async def verified(rt: Runtime) -> None:
    """The start-up check of the drive is done (its transfers would find the drive busy)."""
    if rt.verifying is not None:
        await asyncio.wait_for(asyncio.shield(rt.verifying), 5)


def switched_on(rig: Rig, unit: str = "left") -> None:
    for text in ("SERVO ON ON", "START ON ON"):
        assert rig.sup.apply_text(unit, text) == "", text


def test_the_estop_first_step_switches_nothing_on_it_only_takes_start_off(rig: Rig) -> None:
    """``inputs & ~START`` → ``inputs | ~START`` (word): the first e-stop frame would switch
    on every other bit — brake release, torque — on a drive that had them off."""
    switched_on(rig)  # the brake stays applied
    rig.sup.set_velocity("left", 300, 0)
    rig.run(0.3)
    lay = rig.sup.units["left"].layout
    before = rig.drive("left").inputs
    assert before & lay.start.both and not before & lay.brake_release
    rig.sup.emergency_stop("test")
    rig.run(0.03)  # the e-stop's frame, before the drive reports it stopped
    assert rig.drive("left").inputs == before & ~lay.start.both


def test_a_unit_nobody_owns_is_told_zero_on_both_axes() -> None:
    """``Word(inputs, 0.0, 0.0)`` → ``Word(inputs, 0.0, 1.0)`` (word, not owned): the
    unowned unit's BX would creep at 1 min⁻¹ after its owner fell silent."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    del rig.sup.arbiter.sources["api:left"]  # the rig's standing source: the real default
    switched_on(rig)
    rig.sup.set_velocity("left", 300, 20)
    rig.run(0.3)
    assert rig.drive("left").cmd_raw[1] != 0
    rig.run(0.5)  # the streamed source fell silent: nobody owns the unit
    assert rig.sup.units["left"].setpoint.owner is None
    assert tuple(rig.drive("left").cmd_raw[:2]) == (0, 0)


def test_a_parameter_write_sends_the_safe_word_not_only_the_moving_switches_off(
    rig: Rig,
) -> None:
    """``stopping or written or …`` → ``stopping and written or …`` (restricted): a write
    would leave switches that do not move the motor (here ERROR RESET) on the wire,
    where the safe word has everything off but data select."""
    lay = rig.sup.units["left"].layout
    rig.sup.set_inputs("left", lay.error_reset, lay.error_reset)
    rig.run(0.1)
    assert rig.drive("left").inputs & lay.error_reset
    with rig.sup.param_write("left"):
        rig.run(0.1)
        told = rig.drive("left").inputs
        assert told == lay.safe(told) and not told & lay.error_reset


def test_during_an_estop_harmless_bits_may_still_rise(rig: Rig) -> None:
    """``rising & moving`` → ``rising | moving`` (refuse_inputs): every rising bit would be
    refused while latched, data select and ERROR RESET too. (On the wire the powered-off
    e-stop sends the safe word, so the bit goes out once the e-stop is cleared.)"""
    unit = rig.sup.units["left"]
    lay = unit.layout
    rig.sup.emergency_stop("test")
    rig.sup.set_inputs("left", lay.error_reset, lay.error_reset)  # not refused
    assert unit.inputs & lay.error_reset
    with pytest.raises(CommandError):
        rig.sup.set_inputs("left", lay.servo.both, lay.servo.both)


def test_the_estop_powers_each_unit_off_once() -> None:
    """power_off's three mutants: ``or`` → ``and`` (raises without an e-stop, and is
    "still to be done" again and again), ``return False`` → ``return True``, and
    ``add(unit)`` → ``add(None)``: the second step would be redone on every period."""
    gate = MotionGate()
    assert gate.power_off("left") is False  # no e-stop: nothing to do
    gate.latch(1.0)
    assert gate.power_off("left") is True
    assert gate.power_off("left") is False
    assert gate.power_off("right") is True
    gate.clear()
    assert gate.power_off("left") is False


def test_stopping_is_a_boolean_in_the_state_clients_read(rig: Rig) -> None:
    """``self.stopping = False`` → ``None`` (__init__): the state every client reads
    (``"stopping"`` in service/snapshot.py) would say ``null``, not ``false``."""
    assert rig.sup.stopping is False
    rig.sup.safe_state()
    assert rig.sup.stopping is True


def test_what_the_gate_refuses_says_why_in_words_the_operator_reads(rig: Rig) -> None:
    """The refusals' texts, exactly (mutants that reword or case-change them survived)."""
    unit = rig.sup.units["left"]
    lay = unit.layout
    gate = rig.sup.gate
    with gate.writing(unit):
        assert gate.blocked(unit) == (
            "a parameter write is in flight on unit 'left': SERVO, START and motion are "
            "refused until it ends"
        )
    gate.latch(0.0)
    with pytest.raises(CommandError) as inputs:
        gate.refuse_inputs(unit, unit.inputs | lay.servo.both)
    assert str(inputs.value) == (
        "emergency stop is latched: clear it before SERVO, START or brake release"
    )
    with pytest.raises(CommandError) as motion:
        gate.refuse_motion(unit, 10.0, 0.0)
    assert str(motion.value) == "emergency stop is latched: clear it before commanding motion"
    gate.clear()
    rig.sup.safe_state()
    assert gate.blocked(unit) == "the supervisor is stopping: commands are refused"


def test_a_zero_setpoint_is_zero_on_the_wire_in_either_scale() -> None:
    """Why the ``kind`` mutants of word (``ControlMode.VELOCITY``/``setpoint.kind`` →
    ``None``) are equivalent: every such word has zero setpoints, and zero is the raw 0 in
    the velocity and the current scale alike."""
    assert scaling.VELOCITY.to_raw(0.0) == scaling.CURRENT.to_raw(0.0) == (0, False)


def test_a_write_refused_for_this_supervisors_servo_on_never_reaches_the_drive() -> None:
    """Mutation (b) of docs/mutation.md, the write's lock taken after the write: the
    refusal would come once the drive had been written (``force`` skips the question to
    the drive, so the lock alone decides)."""
    cfg = parse_config(ONE_DRIVE.format(channel="gate-mutants-own"), "o.yaml")

    async def scenario() -> tuple[int, int]:
        async with Runtime(cfg) as rt:
            await verified(rt)
            tel = rt.sims["b"].drives[1].tel
            before = tel.params[SPEED_AY_0]
            ops = ParamOps(rt.supervisor, lambda bus: rt.pumps[bus].wake())
            assert rt.supervisor.apply_text("left", "SERVO ON ON") == ""
            with pytest.raises(ParamFailed, match="commands its servo ON"):
                await ops.write("left", SPEED_AY_0, before + 1, force=True, source="t")
            return before, tel.params[SPEED_AY_0]

    before, after = asyncio.run(scenario())
    assert after == before


def test_servo_on_given_once_a_write_has_begun_is_refused_until_it_ends() -> None:
    """Mutation (b) again, the race of issue 29 (a write, then SERVO ON from another client
    a moment later): from the write's first step the lock refuses SERVO ON."""
    cfg = parse_config(ONE_DRIVE.format(channel="gate-mutants-race"), "r.yaml")

    async def scenario() -> tuple[str, int, str]:
        async with Runtime(cfg) as rt:
            await verified(rt)
            sup = rt.supervisor
            ops = ParamOps(sup, lambda bus: rt.pumps[bus].wake())
            write = asyncio.ensure_future(
                ops.write("left", SPEED_AY_0, 0x00400009, force=False, source="t")
            )
            await asyncio.sleep(0)  # one turn of the loop: the write has begun, not ended
            during = sup.apply_text("left", "SERVO ON ON")
            _, back = await write
            return during, back, sup.apply_text("left", "SERVO ON ON")

    during, back, after = asyncio.run(scenario())
    assert (during, back, after) == (RESPONSE_INVALID, 0x00400009, "")
