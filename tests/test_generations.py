"""Both drive generations end to end: the bits on the wire, the decode, the drive's motion."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest

from abh3_supervisor.clients.decode import decode_file
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.supervisor import SupervisorEvent
from abh3_supervisor.errors import CommandError
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.scheduler.core import FeedbackEvent
from tests.support.rig import TWO_UNITS, Rig, present, set_current, set_velocity

CONFIG = parse_config(TWO_UNITS, "two.yaml")  # left: 2021 travel model; right: 2023 motor model
TOLD = ("SERVO ON ON", "START ON ON", "BRAKE ON ON", "VEL 100 100")
EXPECTED = {  # every bit the four commands set, and the data select already there
    "left": (
        0x10073073,
        ["AY_SERVO_ON", "AY_START", "AY_SELECT0", "AY_SELECT1", "AY_SELECT2", "BX_SERVO_ON",
         "BX_START", "BX_SELECT0", "BX_SELECT1", "BX_SELECT2", "BRAKE_RELEASE"],
    ),
    "right": (
        0x00087373,
        ["AY_SERVO_ON", "AY_START", "AY_SELECT0", "AY_SELECT1", "AY_SELECT2", "BX_SERVO_ON",
         "BX_START", "BX_SELECT0", "BX_SELECT1", "BX_SELECT2", "BRAKE_RELEASE"],
    ),
}  # fmt: skip


@pytest.mark.wallclock
def test_each_generation_gets_its_own_bits_and_the_2023_drive_turns_both_wheels(
    tmp_path: Path,
) -> None:
    record = tmp_path / "both.log"

    async def scenario() -> None:
        async with Runtime(CONFIG, record=record) as rt:
            sup = rt.supervisor
            turning = asyncio.Event()

            def watch(event: SupervisorEvent) -> None:
                fb = sup.units["right"].feedback
                if isinstance(event, FeedbackEvent) and fb and min(fb.vel_a, fb.vel_b) > 99:
                    turning.set()

            sup.subscribe(watch)
            for unit in ("left", "right"):
                for text in TOLD:
                    assert await sup.command(unit, text) == "", (unit, text)
            for unit, (word, _) in EXPECTED.items():
                assert sup.units[unit].inputs == word
            await asyncio.wait_for(turning.wait(), 5)

    asyncio.run(scenario())
    decoded = [json.loads(line) for line in decode_file(record, CONFIG, as_json=True)]
    for unit, (word, names) in EXPECTED.items():
        commands = [r for r in decoded if r["kind"] == "dp0_command" and r["unit"] == unit]
        moving = [r for r in commands if r["values"]["cmd_ay"] == 100.0]
        assert moving, unit
        assert {r["values"]["inputs"] for r in moving} == {f"0x{word:08X}"}
        assert moving[-1]["flags"]["inputs"] == names
        assert moving[-1]["protocol"] == CONFIG.units[unit].protocol.value
    # the 2023 drive's replies carry its control word, named in the 2023 layout
    replies = [r for r in decoded if r["kind"] == "dp0_reply" and r["unit"] == "right"]
    assert any({"AY_BUSY", "BX_BUSY"} <= set(r["flags"].get("control", [])) for r in replies)


def test_bits_a_generation_does_not_define_never_reach_a_drive(rig: Rig) -> None:
    rig.run(0.1)
    sent = len(rig.timeline.frames)
    with pytest.raises(CommandError, match=r"bits 0x00800000 are not defined in the 2023"):
        rig.sup.set_inputs("right", 1 << 23, 1 << 23)
    with pytest.raises(CommandError, match=r"bits 0x08000000 are not defined in the 2021"):
        rig.sup.set_inputs("left", 0xFFFFFFFF, 1 << 27)  # travel model: control word only
    assert rig.sup.apply_text("right", "SERVO ON ON") == ""
    before = rig.sup.units["right"].inputs
    rig.sup.set_inputs("right", 0, 0xFFFFFFFF)  # clearing never sets an undefined bit
    assert rig.sup.units["right"].inputs == 0 != before
    rig.run(0.1)
    assert len(rig.timeline.frames) > sent


def test_the_whole_wire_range_is_reachable(rig: Rig) -> None:
    assert (
        set_velocity(rig.sup, "left", -6553.6, 6553.4, source=present(rig.sup, "left")).clamped
        is False
    )
    assert rig.sup.apply_text("left", "TORQUE ON ON") == ""
    assert (
        set_current(rig.sup, "left", -327.68, 327.67, source=present(rig.sup, "left")).clamped
        is False
    )
    result = set_current(
        rig.sup, "left", -400, 0, source=present(rig.sup, "left")
    )  # beyond the wire: scaled to it
    assert result.clamped and result.ay == pytest.approx(-327.68)


@pytest.mark.wallclock
def test_decode_keeps_buses_apart(tmp_path: Path) -> None:
    """The same address on two buses, with different generations and hosts."""
    config = parse_config(
        """
buses:
  left: {interface: virtual, channel: dec-left, simulate: true}
  right: {interface: virtual, channel: dec-right, simulate: true}
units:
  - {name: l21, bus: left, abh3_id: 1}
  - {name: r23, bus: right, abh3_id: 1, host_id: 7, protocol: "2023"}
  - {name: r2, bus: right, abh3_id: 2, host_id: 7, protocol: "2023"}
""",
        "two-buses.yaml",
    )
    record = tmp_path / "buses.log"

    async def scenario() -> None:
        async with Runtime(config, record=record) as rt:
            sup = rt.supervisor
            since = sup.clock()
            assert all(await asyncio.gather(*(sup.wait_exchange(n, since, 2) for n in sup.units)))

    asyncio.run(scenario())
    decoded = [json.loads(line) for line in decode_file(record, config, as_json=True)]
    commands = {r["unit"]: r for r in decoded if r["kind"] == "dp0_command"}
    assert set(commands) == {"l21", "r23", "r2"}
    for unit in ("l21", "r23", "r2"):
        names = commands[unit]["flags"]["inputs"]
        assert "AY_TORQUE" not in names and not any(n.startswith("bit") for n in names), unit
    replies = {r["unit"] for r in decoded if r["kind"] == "dp0_reply"}
    assert replies == {"l21", "r23", "r2"}  # r2's reply is no command to a drive "id7"
