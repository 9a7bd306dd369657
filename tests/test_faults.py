"""Fault paths: what the simulated drive does, not only what the log says (issue 11)."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from pathlib import Path

import pytest

from abh3_supervisor.config import load_config, parse_config
from abh3_supervisor.config.model import WIRING_KINDS, Fault, FaultKind
from abh3_supervisor.core.supervisor import FlagChange, Notice
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.headless import run_headless
from abh3_supervisor.scheduler.core import BusScheduler, GapEvent, HealthEvent, MalformedEvent
from tests.support.rig import TWO_UNITS, Rig

SCHEDULER = 0  # the Rig adds the scheduler first, the simulated drives second


def drive_both(rig: Rig) -> None:
    for unit, vel in (("left", "VEL 300 0"), ("right", "VEL 200 200")):
        for text in ("SERVO ON ON", "START ON ON", vel):
            assert rig.sup.apply_text(unit, text) == ""


def speeds(rig: Rig) -> list[float]:
    return [abs(v) for unit in ("left", "right") for v in rig.drive(unit).vel]


def test_a_send_outage_longer_than_the_drive_timeout_never_restarts_the_drives(rig: Rig) -> None:
    drive_both(rig)
    rig.run(1.0)
    assert min(speeds(rig)[0:2]) > 100 and min(speeds(rig)[2:]) > 100  # moving
    outage = rig.timeline.now
    rig.timeline.refuse_sends(SCHEDULER, outage, outage + 0.8)  # within the 1 s offline time
    rig.run(0.8)
    # the drives stopped on their own 500 ms command-zero timeout …
    assert max(speeds(rig)) < 1.0
    assert all(rig.sup.units[u].online for u in ("left", "right"))  # never went offline
    rig.run(2.0)  # … and sending works again: they must stay stopped
    assert max(speeds(rig)) < 1.0
    gaps = [e for e in rig.events if isinstance(e, GapEvent)]
    assert [(e.unit, e.started) for e in gaps if e.started] == [("left", True), ("right", True)]
    # declared at the outage bound (OUTAGE_S, here the drives' own 500 ms): a drive that
    # lost its power and booted within its timeout would otherwise take our SERVO again
    assert all(outage + 0.45 <= e.t <= outage + 0.55 for e in gaps if e.started)
    assert any(
        isinstance(e, Notice) and "SERVO, START and brake release off" in e.message
        for e in rig.events
    )
    # no automatic restart: the drive may have lost its power, so its switches are gone
    # too; motion is refused until they are given again, and then it moves
    assert rig.sup.apply_text("left", "VEL 100 0") == "Invalid Command."
    for text in ("SERVO ON ON", "START ON ON", "VEL 100 0"):
        assert rig.sup.apply_text("left", text) == ""
    rig.run(0.5)
    assert abs(rig.drive("left").vel[0]) > 50


def test_a_short_outage_within_the_drive_timeout_keeps_the_setpoint(rig: Rig) -> None:
    drive_both(rig)
    rig.run(1.0)
    rig.timeline.refuse_sends(SCHEDULER, rig.timeline.now, rig.timeline.now + 0.2)
    rig.run(1.0)
    assert not [e for e in rig.events if isinstance(e, GapEvent)]
    assert rig.sup.units["left"].setpoint.ay == 300.0
    assert min(speeds(rig)[0:2]) > 100


def test_wrong_length_replies_never_count(rig: Rig, caplog: object) -> None:
    rig.drive("left").silent = True
    reply = ids.dp0_reply_id(1, 2)
    for i in range(50):  # spoofed DLC-0 and short replies, a flood
        rig.sup.schedulers["b"].on_frame(reply, b"" if i % 2 else b"\x00" * 7, 0.001 * i)
        rig.sup.dispatch("b")
    rig.run(1.5)
    slot = rig.scheduler.slots["left"]
    assert slot.stats.malformed == 50 and slot.stats.replies == 0
    assert rig.sup.units["left"].online is False  # silent: never made online by junk
    assert rig.sup.units["left"].feedback is None
    notices = [e for e in rig.events if isinstance(e, Notice) and "malformed" in e.message]
    assert len(notices) == 1 and notices[0].level == logging.WARNING  # once per second
    assert len([e for e in rig.events if isinstance(e, MalformedEvent)]) == 50


def test_broadcast_7_proves_nothing(rig: Rig) -> None:
    rig.drive("left").silent = True
    rig.sup.schedulers["b"].on_frame(ids.broadcast_id(1, 5, 7), b"\x01", 0.0)
    rig.sup.dispatch("b")
    assert rig.sup.units["left"].online is None
    assert rig.sup.units["left"].status[7][1] == frames.Brd7(b"\x01")


def test_a_flapping_flag_word_gives_a_few_lines_per_second(rig: Rig) -> None:
    from abh3_supervisor.core.eventlog import EventLog
    from abh3_supervisor.core.supervisor import FlagChange

    events = EventLog(rig.sup)
    lines = []
    for i in range(100):  # error bit 0 toggling every 10 ms for a second
        change = FlagChange("left", i * 0.01, "error", i % 2, (i + 1) % 2)
        if (line := events.line(change)) is not None:
            lines.append(line[1])
    assert (
        lines
        == [
            "unit left: error +A_MECH_LOCK (A mechanical lock)",
            "unit left: error -A_MECH_LOCK (A mechanical lock)",
        ]
        * 2
    )  # a set and its clear both show
    line = events.line(FlagChange("left", 1.0, "error", 0, 1))
    assert line is not None and line[1].endswith("(96 more like it since the last line not shown)")
    other = events.line(FlagChange("right", 0.5, "error", 0, 1))  # another unit: its own
    assert other is not None


def rig_with(*faults: Fault) -> Rig:
    config = parse_config(TWO_UNITS, "two.yaml")
    bus = config.buses["b"]
    assert bus.simulate is not None
    sim = dataclasses.replace(bus.simulate, faults=faults)
    return Rig(dataclasses.replace(config, buses={"b": dataclasses.replace(bus, simulate=sim)}))


def test_scripted_silence_takes_a_unit_offline_and_back() -> None:
    rig = rig_with(Fault(FaultKind.SILENT, at_s=1.0, for_s=2.0, unit="left"))
    rig.run(4.0)
    health = [(e.unit, e.online) for e in rig.events if isinstance(e, HealthEvent)]
    assert ("left", False) in health and health[-1] == ("left", True)
    assert ("right", False) not in health  # only the unit named


def test_scripted_malformed_replies_are_counted_never_taken() -> None:
    rig = rig_with(Fault(FaultKind.MALFORMED_REPLIES, at_s=0.5, for_s=1.2))
    rig.run(0.5)
    replies = {u: rig.scheduler.slots[u].stats.replies for u in ("left", "right")}
    rig.run(1.2)
    for unit in ("left", "right"):
        stats = rig.scheduler.slots[unit].stats
        assert stats.malformed >= 10  # an exchange waits reply_timeout_ms for each
        assert stats.replies == replies[unit]  # not one taken as a reply
        assert rig.sup.units[unit].online is False  # junk only: offline, as if silent
    rig.run(1.2)  # an offline unit is probed once per timeout_ms
    assert all(rig.sup.units[u].online for u in ("left", "right"))  # back with the fault


def test_scripted_error_bits_stop_the_drive_while_present() -> None:
    rig = rig_with(Fault(FaultKind.ERROR_BITS, at_s=1.0, for_s=1.0, unit="right", bits=1 << 7))
    drive_both(rig)
    rig.run(1.5)
    assert rig.drive("right").vel == [0.0, 0.0] or max(map(abs, rig.drive("right").vel)) < 200
    errors = [e for e in rig.events if isinstance(e, FlagChange) and e.word == "error"]
    assert any(e.unit == "right" and e.set_bits == 1 << 7 for e in errors)
    rig.run(1.0)
    assert rig.sup.units["right"].words["error"] == 0  # gone with the fault


def test_scripted_slow_replies_count_as_timeouts() -> None:
    rig = rig_with(Fault(FaultKind.SLOW_REPLIES, at_s=0.5, for_s=1.0, delay_ms=60))
    rig.run(0.5)
    assert (rig.scheduler.slots["left"].stats.rtt_ms(99) or 0) < 5
    rig.run(1.5)
    stats = rig.scheduler.slots["left"].stats
    assert (stats.rtt_ms(99) or 0) > 55 and stats.timeouts == 0  # slow, within reply_timeout_ms


@pytest.mark.wallclock
def test_a_scripted_send_outage_on_the_virtual_bus_stops_and_does_not_restart() -> None:
    config = parse_config(TWO_UNITS, "two.yaml")
    bus = config.buses["b"]
    assert bus.simulate is not None
    outage = Fault(FaultKind.BUS_SEND_ERROR, at_s=0.6, for_s=0.8)
    sim = dataclasses.replace(bus.simulate, faults=(outage,))
    config = dataclasses.replace(config, buses={"b": dataclasses.replace(bus, simulate=sim)})
    rt = Runtime(config)
    seen: dict[str, list[float]] = {"during": [], "after": []}

    async def scenario() -> None:
        async with rt:
            sup, loop = rt.supervisor, asyncio.get_running_loop()
            start = loop.time()
            for text in ("SERVO ON ON", "START ON ON", "VEL 300 0"):
                assert await sup.command("left", text) == ""
            gap = asyncio.Event()
            sup.subscribe(lambda e: gap.set() if isinstance(e, GapEvent) and e.started else None)
            await asyncio.wait_for(gap.wait(), 5)
            seen["during"] = list(rt.sims["b"].drives[1].vel)
            resumed = asyncio.Event()
            sup.subscribe(
                lambda e: resumed.set() if isinstance(e, GapEvent) and not e.started else None
            )
            await asyncio.wait_for(resumed.wait(), 5)
            assert loop.time() - start >= 1.39  # the outage ended (less the timer's 1 ms grain)
            await sup.wait_exchange("left", loop.time(), 1.0)
            seen["after"] = list(rt.sims["b"].drives[1].vel)
            assert sup.units["left"].setpoint.ay == 0.0

    asyncio.run(scenario())
    assert max(map(abs, seen["after"])) < max(map(abs, seen["during"])) or seen["after"] == [0, 0]
    assert rt.sims["b"].drives[1].cmd_raw == (0, 0)  # the drive was never told the old speed


FAULTY = """
buses:
  b:
    interface: virtual
    channel: faults-{name}
    simulate:
      faults: {faults}
units:
  - {{name: left, abh3_id: 1, startup: ["SERVO ON ON", "START ON ON", "VEL 300 0"]}}
  - {{name: right, abh3_id: 3, protocol: "2023"}}
"""


def faulty(faults: str, name: str = "t") -> str:
    return FAULTY.format(faults=faults, name=name)


def test_faults_from_the_yaml() -> None:
    config = parse_config(
        faulty(
            "[{kind: bus_send_error, at_s: 2, for_s: 0.8},"
            " {kind: error_bits, at_s: 1, for_s: 2, unit: left, bits: 0x80},"
            " {kind: slow_replies, at_s: 0, for_s: 1, delay_ms: 20}]"
        ),
        "f.yaml",
    )
    sim = config.buses["b"].simulate
    assert sim is not None
    assert sim.faults == (
        Fault(FaultKind.BUS_SEND_ERROR, 2.0, 0.8),
        Fault(FaultKind.ERROR_BITS, 1.0, 2.0, unit="left", bits=0x80),
        Fault(FaultKind.SLOW_REPLIES, 0.0, 1.0, delay_ms=20.0),
    )


def test_shipped_faults_config_is_valid() -> None:
    """configs/faults.yaml rehearses every fault in time; the wiring faults, which last,
    are commissioning's (tests/test_commission_sim.py)."""
    path = Path(__file__).parent.parent / "configs" / "faults.yaml"
    sim = load_config(path).buses["sim"].simulate
    assert sim is not None and {f.kind for f in sim.faults} == set(FaultKind) - WIRING_KINDS


@pytest.mark.parametrize(
    ("faults", "message"),
    [
        ("[{kind: meltdown, at_s: 1, for_s: 1}]", "faults[0].kind: 'meltdown' is not one of"),
        ("[{kind: silent, for_s: 1}]", "faults[0].at_s: missing"),
        ("[{kind: silent, at_s: 1, for_s: 0}]", "faults[0].for_s: 0 is out of range"),
        ("[{kind: silent, at_s: 1, for_s: 1, unit: middle}]", "no unit 'middle' on bus b"),
        ("[{kind: silent, at_s: 1, for_s: 1, bits: 4}]", "bits: does not apply to kind silent"),
        ("[{kind: bus_send_error, at_s: 1, for_s: 1, unit: left}]", "a fault of the whole bus"),
        ("{kind: silent}", "faults: expected a list"),
    ],
)
def test_bad_faults_are_config_errors(faults: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(faulty(faults), "f.yaml")
    assert any(p.startswith("f.yaml:") and message in p for p in info.value.problems), info.value


@pytest.mark.wallclock
def test_headless_shows_each_fault_and_recovers_with_exit_0(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = parse_config(
        faulty(
            "[{kind: bus_send_error, at_s: 0.5, for_s: 0.8},"
            " {kind: malformed_replies, at_s: 1.6, for_s: 0.2, unit: right}]",
            "ok",
        ),
        "f.yaml",
    )
    with caplog.at_level(logging.INFO):
        code = asyncio.run(run_headless(config, duration=2.5, record=None, status_interval=0))
    assert code == 0
    text = caplog.text
    assert "send failed (simulated fault" in text
    assert "unit left: no exchange completed for 500 ms" in text
    assert "SERVO, START and brake release off: switch them on again" in text
    assert "unit left: exchanges again after the gap" in text
    assert "unit right: malformed dp0 reply ignored" in text
    assert text.count("stop frame confirmed by the drive") == 2


@pytest.mark.wallclock
def test_a_fault_that_prevents_a_stop_ends_with_exit_3(caplog: pytest.LogCaptureFixture) -> None:
    config = parse_config(faulty("[{kind: silent, at_s: 0.5, for_s: 100, unit: right}]", "x"))
    with caplog.at_level(logging.INFO):
        code = asyncio.run(run_headless(config, duration=1.0, record=None, status_interval=0))
    assert code == 3
    assert "unit right: stop frame sent, not confirmed" in caplog.text
    assert "unit left: stop frame confirmed by the drive" in caplog.text


@pytest.mark.parametrize("outage", [0.41, 0.45, 0.49, 0.6])
def test_the_first_frame_after_a_gap_never_carries_the_old_command(outage: float) -> None:
    """At 10 Hz the first frame after an outage may be the one that reveals the gap."""
    config = parse_config(
        """
buses: {b: {interface: virtual, channel: t, simulate: true}}
units:
  - {name: u, abh3_id: 1, command_rate_hz: 10, broadcast: {mask: 0x01, rate_hz: 1}}
""",
        "g.yaml",
    )
    rig = Rig(config)
    for text in ("SERVO ON ON", "START ON ON", "VEL 300 0"):
        assert rig.sup.apply_text("u", text) == ""
    rig.run(1.0)
    assert rig.drive("u").vel[0] > 250
    start = rig.timeline.now
    rig.timeline.refuse_sends(SCHEDULER, start, start + outage)
    rig.run(2.0)
    cmd_id = ids.dp0_command_id(1, 2)
    after = [
        frames.decode_dp0_command(f.data, rig.config.units["u"].protocol)
        for f in rig.timeline.frames
        if f.arbitration_id == cmd_id and f.start >= start + 0.495
    ]
    assert after and all(isinstance(c, frames.Dp0Command) and c.cmd_ay == 0 for c in after)
    assert max(map(abs, rig.drive("u").vel)) < 1.0


def test_a_stalled_host_sends_zero_first_when_it_wakes_after_the_gap() -> None:
    """kill -STOP, a frozen loop: the poll that reveals the gap also sends a command."""
    config = parse_config(TWO_UNITS, "two.yaml")
    sched = BusScheduler(config.units_on("b"), 0.0)
    moving = frames.encode_dp0_command(1500, 0, 0x00073073)  # 300 min⁻¹, servo + start
    sched.set_payload("left", moving)
    sent = dict(sched.poll(0.0))
    assert sent[ids.dp0_command_id(1, 2)] == moving
    sched.on_frame(ids.dp0_reply_id(1, 2), bytes(8), 0.001)  # answered: the drive had it
    late = dict(sched.poll(1.2))  # the host wakes 1.2 s later: past the drive's timeout
    assert late[ids.dp0_command_id(1, 2)] == bytes(4) + moving[4:]  # zero, inputs kept
    assert any(isinstance(e, GapEvent) and e.started for e in sched.drain_events())


def test_the_simulated_drive_keeps_its_units_drive_timeout() -> None:
    config = parse_config(
        """
buses: {b: {interface: virtual, channel: t, simulate: true}}
units:
  - {name: u, abh3_id: 1, drive_timeout_ms: 750}
  - {name: v, abh3_id: 3}
""",
        "d.yaml",
    )
    rig = Rig(config)
    assert (rig.drive("u").command_zero_ms, rig.drive("v").command_zero_ms) == (750, 500)
    for text in ("SERVO ON ON", "START ON ON", "VEL 300 0"):
        rig.sup.apply_text("u", text)
    rig.run(1.0)
    start = rig.timeline.now
    rig.timeline.refuse_sends(SCHEDULER, start, start + 0.6)  # within 750 ms, past 500
    rig.run(0.59)
    assert rig.drive("v").command_zero_fired()  # 500 ms: v's drive stopped itself …
    assert not rig.drive("u").command_zero_fired()  # … u's (750 ms) did not
    assert rig.drive("u").vel[0] > 250
    rig.run(1.0)
    # the supervisor took both silences as outages (OUTAGE_S): no automatic restart
    gaps = [e.unit for e in rig.events if isinstance(e, GapEvent) and e.started]
    assert sorted(gaps) == ["u", "v"]
    assert max(map(abs, rig.drive("u").vel)) < 1.0  # so u stands too, until switched on
