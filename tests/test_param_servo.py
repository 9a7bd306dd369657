"""Parameter writes decide from the drive, now: the servo is asked of the drive at the
moment of the write (a 2023 DP0 reply after the question, a 2021 broadcast 1 asked for
then), whatever the broadcast mask polls; an old word never decides.

Two supervisors share one virtual bus, as `abh3 run` and `abh3 param -c` did before a
second host was detected (core/foreign.py): one commands the simulated drives, the other
(every unit a monitor) writes parameters.
"""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from abh3_supervisor.clients.param import monitor_only
from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.param_ops import ParamFailed, ParamOps

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROUNDS = 25  # per generation and mask; 100 of each were run once for the closing note
SPEED_AY_0 = 0x5000

RIG = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: {simulate}}}
units:
  - {{name: old, abh3_id: 1, command_rate_hz: 100, broadcast: {{mask: {mask}, rate_hz: 2}}}}
  - {{name: new, abh3_id: 3, protocol: "2023", velocity_model: motor, command_rate_hz: 100,
     broadcast: {{mask: {mask}, rate_hz: 2}}}}
"""


async def started(rt: Runtime) -> None:
    """Once a service's start-up check has read its drives: a tool with the same host
    address starting a transfer meanwhile would find the drive busy (docs/parameters.md)."""
    if rt.verifying is not None:
        await asyncio.wait_for(asyncio.shield(rt.verifying), 5)


@pytest.mark.parametrize("mask", ["0x7f", "0x04"])
def test_servo_on_then_an_immediate_write_is_refused_and_off_then_write_succeeds(
    mask: str,
) -> None:
    channel = f"servo-race-{mask}"
    driving = parse_config(RIG.format(channel=channel, simulate="true", mask=mask), "d.yaml")
    writing = monitor_only(
        parse_config(RIG.format(channel=channel, simulate="false", mask=mask), "w.yaml")
    )

    async def scenario() -> dict[str, tuple[int, int]]:
        counts: dict[str, tuple[int, int]] = {}
        async with Runtime(driving) as drive_rt, Runtime(writing) as write_rt:
            await started(drive_rt)  # its start-up check of the drives is done (core/verify.py)
            sup = drive_rt.supervisor
            # the writer's parameter sessions are another host's to the commanding one, which
            # would stop its drives (core/foreign.py; `abh3 param -c` now refuses such a
            # bus): here it is told to watch no drive, to test the servo question alone
            sup.schedulers["b"].foreign.drives.clear()
            ops = ParamOps(write_rt.supervisor, lambda bus: write_rt.pumps[bus].wake())
            for unit in ("old", "new"):
                refused = written = 0
                for i in range(ROUNDS):
                    assert await sup.command(unit, "SERVO ON ON") == ""  # the drive has it
                    with pytest.raises(ParamFailed, match="reports its servo ON"):
                        await ops.write(unit, SPEED_AY_0, 0x00400008 + i, force=False, source="t")
                    refused += 1
                    assert await sup.command(unit, "SERVO OFF OFF") == ""
                    word = 0x00400008 + i
                    _, back = await ops.write(unit, SPEED_AY_0, word, force=False, source="t")
                    assert back == word
                    written += 1
                counts[unit] = (refused, written)
        return counts

    assert asyncio.run(scenario()) == {"old": (ROUNDS, ROUNDS), "new": (ROUNDS, ROUNDS)}


def test_a_drive_that_does_not_answer_the_question_is_not_written() -> None:
    """No answer to 'is your servo on?' within the unit's timeout: refused, nothing sent."""
    cfg = parse_config(RIG.format(channel="servo-silent", simulate="true", mask="0x01"), "s.yaml")
    cfg = dataclasses.replace(
        cfg, units={n: dataclasses.replace(u, timeout_ms=200) for n, u in cfg.units.items()}
    )

    async def scenario() -> None:
        async with Runtime(cfg) as rt:
            ops = ParamOps(rt.supervisor, lambda bus: rt.pumps[bus].wake())
            for unit, cfg_unit in cfg.units.items():
                rt.sims["b"].drives[cfg_unit.abh3_id].silent = True
                with pytest.raises(ParamFailed, match="did not answer whether its servo is on"):
                    await ops.write(unit, SPEED_AY_0, 1, force=False, source="t")

    asyncio.run(scenario())


def test_the_supervisors_own_servo_on_command_refuses_a_write_before_the_drive_is_asked() -> None:
    cfg = parse_config(RIG.format(channel="servo-own", simulate="true", mask="0x7f"), "o.yaml")

    async def scenario() -> None:
        async with Runtime(cfg) as rt:
            sup = rt.supervisor
            ops = ParamOps(sup, lambda bus: rt.pumps[bus].wake())
            sup.apply_text("old", "SERVO ON ON")  # not even sent yet
            with pytest.raises(ParamFailed, match="commands its servo ON"):
                await ops.write("old", SPEED_AY_0, 1, force=False, source="t")

    asyncio.run(scenario())
