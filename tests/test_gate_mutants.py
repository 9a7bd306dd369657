"""The mutants of the motion gate and of the arbitration that feeds it which the other
tests let survive (docs/mutation.md): each test here fails under the mutation named in its
docstring. Judged by what the simulated drive was told where the wire shows it, on a fake
clock; the arbitration (core/inputs.py's InputArbiter) on a clock the test sets."""

from __future__ import annotations

import asyncio

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Fault, FaultKind, VerifyMode
from abh3_supervisor.core.commands import RESPONSE_INVALID, VelocityCommand
from abh3_supervisor.core.gate import MotionGate
from abh3_supervisor.core.inputs import ZERO, InputArbiter, InputCommand, InputSource
from abh3_supervisor.core.verify import State, Verification
from abh3_supervisor.core.verifying import verify_units
from abh3_supervisor.errors import CommandError
from abh3_supervisor.plugin_host.feed import InputFeed
from abh3_supervisor.protocol import scaling
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.stopping import CONFIRMED
from abh3_supervisor.service.param_ops import ParamFailed, ParamOps
from tests.support.rig import TWO_UNITS, Rig, set_velocity, streamed

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
    set_velocity(rig.sup, "left", 300, 0)
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
    switched_on(rig)
    set_velocity(rig.sup, "left", 300, 20, streamed(rig.sup, "left"))
    rig.run(0.3)
    assert rig.drive("left").cmd_raw[1] != 0
    rig.run(0.5)  # the streamed source fell silent: nobody owns the unit
    assert rig.sup.units["left"].setpoint.owner is None
    assert tuple(rig.drive("left").cmd_raw[:2]) == (0, 0)


def test_a_parameter_write_sends_the_safe_word_not_only_the_moving_switches_off(
    rig: Rig,
) -> None:
    """``stopping or written or …`` → ``stopping and written or …`` (restricted): a write
    would leave switches that do not move the motor (here the command polarity) on the
    wire, where the safe word has everything off but data select (and an error reset)."""
    lay = rig.sup.units["left"].layout
    rig.sup.set_inputs("left", lay.reverse.both, lay.reverse.both)
    rig.run(0.1)
    assert rig.drive("left").inputs & lay.reverse.both
    with rig.sup.param_write("left"):
        rig.run(0.1)
        told = rig.drive("left").inputs
        assert told == lay.safe(told) and not told & lay.reverse.both


def test_during_an_estop_harmless_bits_may_still_rise(rig: Rig) -> None:
    """``rising & moving`` → ``rising | moving`` (refuse_inputs): every rising bit would be
    refused while latched, data select and ERROR RESET too. (An admitted error reset goes
    out even once the e-stop has powered the unit off: the answer is the truth.)"""
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


class Quiet(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


class Arbitration:
    """An InputArbiter on a clock the test sets; what it applied to each unit, in order."""

    def __init__(self, *, refuse: bool = False) -> None:
        self.now = 0.0
        self.applied: list[tuple[str, InputCommand]] = []
        self.rearmed = 0

        def apply(unit: str, command: InputCommand) -> bool | None:
            self.applied.append((unit, command))
            return False if refuse else None

        self.arb = InputArbiter(apply, lambda: self.now, on_change=self._rearm)

    def _rearm(self) -> None:
        self.rearmed += 1

    def add(
        self, name: str, units: tuple[str, ...], priority: int = 0, timeout: float = 0.5
    ) -> None:
        self.arb.add(Quiet(name, units, priority, timeout))

    def at(self, t: float) -> Arbitration:
        self.now = t
        return self


def test_a_standing_command_behind_an_owner_that_fell_silent_does_not_come_back() -> None:
    """_decide, ``not owner.fresh`` → ``owner.fresh``, and ``taker = …`` → ``None``: the
    client's value, given while the stick drove the unit, would move it once the stick
    fell silent — a value that never drove the unit, from before the stop."""
    a = Arbitration()
    a.add("stick", ("u",), priority=1)
    a.add("client", ("u",))
    a.arb.submit("stick", VelocityCommand(300, 0), 0.0)  # streamed: silent from now on
    a.arb.submit("client", VelocityCommand(100, 0), 0.1, standing=True)  # behind the stick
    assert a.arb.owner("u") == "stick"
    a.arb.touch("client", 0.4)
    a.arb.poll(a.at(0.55).now)  # the stick lapsed at 0.5; the client is still alive
    assert a.applied[-1] == ("u", ZERO) and a.arb.owner("u") is None


def test_a_standing_command_given_after_the_owner_fell_silent_takes_the_unit_and_keeps_it() -> None:
    """_decide, ``taker.heard < now`` → ``<=``: the command given at the very moment would be
    dropped; ``s.heard < replaced`` → ``<=``: it would be dropped at the next decision."""
    a = Arbitration()
    a.add("stick", ("u",), priority=1)
    a.add("client", ("u",))
    a.arb.submit("stick", VelocityCommand(300, 0), 0.0)
    a.arb.submit("client", VelocityCommand(100, 0), 1.0, standing=True)  # no poll between
    assert a.arb.owner("u") == "client"
    a.arb.touch("client", 1.2)
    a.arb.poll(1.2)
    assert a.arb.owner("u") == "client"
    assert a.applied[-1] == ("u", VelocityCommand(100, 0))


def test_one_decision_covers_every_unit_after_one_that_did_not_change() -> None:
    """_decide, ``continue`` → ``break``: the units after an unchanged one would not be
    decided, and a lapsed stream on them would go on moving them. (``submit_now`` too.)"""
    a = Arbitration()
    a.add("left-stick", ("a",), timeout=10.0)
    a.add("right-stick", ("b",))
    a.arb.submit_now("left-stick", VelocityCommand(50, 0))
    a.arb.submit_now("right-stick", VelocityCommand(60, 0))
    assert a.arb.owner("b") == "right-stick"
    a.arb.poll(a.at(1.0).now)  # "a" unchanged, then "b" lapsed
    assert a.applied[-1] == ("b", ZERO) and a.arb.owner("b") is None


def test_a_command_the_unit_refused_is_not_its_command_and_nobody_owns_it() -> None:
    """_decide, ``current[unit] = None`` → ``""`` after a refusal, and owner's
    ``None if current is None`` → always ``current[0]``: owner() would raise."""
    a = Arbitration(refuse=True)
    a.add("client", ("u",))
    assert a.arb.owner("u") is None  # nobody ever drove it
    a.arb.submit("client", VelocityCommand(100, 0), 0.0)
    assert a.arb.owner("u") is None
    a.arb.submit("client", VelocityCommand(100, 0), 0.1)  # the same again: applied anew
    assert a.applied == [("u", VelocityCommand(100, 0))] * 2


def test_proof_of_life_moves_the_deadline_of_a_standing_command() -> None:
    """touch, ``command is not None`` → ``is None``: the expiry moved but the deadline timer
    would not be re-armed for it."""
    a = Arbitration()
    a.add("client", ("u",))
    a.arb.submit("client", VelocityCommand(100, 0), 0.0, standing=True)
    before = a.rearmed
    a.arb.touch("client", 0.3)
    assert a.rearmed == before + 1 and a.arb.next_deadline() == 0.8


def test_units_left_behind_by_a_retarget_stop_and_the_new_ones_are_driven() -> None:
    """retarget_now's mutants (no test in the fast selection called it): the unit left
    behind must get zero, the new one the source's command."""
    a = Arbitration()
    a.add("keys", ("a",))
    a.arb.submit("keys", VelocityCommand(70, 0), 0.0)
    a.arb.retarget_now("keys", ("b",))
    assert a.applied[-2:] == [("a", ZERO), ("b", VelocityCommand(70, 0))]
    assert (a.arb.owner("a"), a.arb.owner("b")) == (None, "keys")


def test_a_source_that_names_no_priority_has_the_documented_default() -> None:
    """InputSource, ``priority: int = 0`` → ``1``: every source that names none (the public
    API's ``api:<unit>``, a third party's) would outrank the plugins that say 0."""
    assert Quiet("x", ("u",)).priority == 0  # docs/plugins.md: InputSource(…, priority=0, …)


def test_a_held_unit_takes_only_a_command_given_after_the_hold() -> None:
    """Mutation (a) of docs/mutation.md, ``InputArbiter.hold`` a no-op: the stream heard
    before the e-stop, hold or write would still own the unit and come back."""
    a = Arbitration()
    a.add("stick", ("u",), timeout=10.0)
    a.arb.submit("stick", VelocityCommand(250, 0), 0.0)
    a.arb.hold("u")
    assert a.arb.owner("u") is None
    a.arb.poll(a.at(1.0).now)  # the stream is still fresh: it does not count any more
    assert a.arb.owner("u") is None and a.applied == [("u", VelocityCommand(250, 0))]
    a.arb.submit("stick", VelocityCommand(250, 0), 1.0)  # the same value, given after
    assert a.arb.owner("u") == "stick" and len(a.applied) == 2


def test_a_check_cut_off_by_its_deadline_is_not_verified_and_holds_the_unit() -> None:
    """``DriveCheck.abandon``, ``if not self.finished`` → ``if self.finished`` (found by a
    partial run over verify.py, docs/mutation.md): a check still reading a slow drive at
    the deadline would never finish — the caller would fail instead of holding the unit."""
    text = ONE_DRIVE.format(channel="gate-mutants-slow")
    cfg = parse_config(text.replace("rate_hz: 2}}", "rate_hz: 2}, verify: refuse}"), "s.yaml")
    assert cfg.units["left"].verify is VerifyMode.REFUSE

    async def scenario() -> tuple[Verification, str | None]:
        async with Runtime(cfg) as rt:
            await verified(rt)
            drive = rt.sims["b"].drives[1]
            drive.faults = (Fault(FaultKind.TP_SLOW_DT, 0.0, 1e6, delay_ms=200.0),)
            got = await verify_units(rt.supervisor, ["left"], deadline=0.3)
            return got["left"], rt.supervisor.units["left"].verify.holds()

    v, held = asyncio.run(scenario())
    assert v.state is State.NOT_VERIFIED and v.reason == "no complete answer within 0.3 s"
    assert held is not None and "could not be verified" in held


def test_a_2021_drive_polling_no_broadcast_1_confirms_its_stop_when_asked() -> None:
    """``_send_stop`` (found by a partial run over stopping.py, docs/mutation.md),
    ``brd1_inputs is None`` → ``is not None`` and ``poll_frames[1]`` → ``[2]``: a 2021
    drive whose mask polls no broadcast 1 would never be asked for the control word that
    confirms its stop, and the way out would report it unconfirmed (exit 3)."""
    text = ONE_DRIVE.format(channel="gate-mutants-stop").replace("mask: 0x7f", "mask: 0x01")
    rt = Runtime(parse_config(text, "b.yaml"))

    async def scenario() -> None:
        async with rt:
            await verified(rt)
            sup = rt.supervisor
            assert await sup.wait_exchange("left", sup.clock(), 2.0)
            assert await sup.command("left", "SERVO ON ON") == ""

    asyncio.run(scenario())
    assert rt.stop_report == {"left": CONFIRMED}
