"""A supervisor with ``interface: wacousb`` drives simulated units through the emulated
adapter: every frame the adapter receives is well framed with a valid CRC."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.state import Feedback
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.simulator import SimBus
from tests.support.buses import BusNotices, drives_on
from tests.support.rig import present
from tests.wacousb_emulator import AdapterEmulator, check_host_frame

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes


def reached(feedback: Feedback | None, vel_y: float, vel_a: float) -> bool:
    return (
        feedback is not None
        and abs(feedback.vel_y - vel_y) < 1.0
        and abs(feedback.vel_a - vel_a) < 1.0
    )


def test_a_supervisor_drives_simulated_units_through_the_adapter(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    link = tmp_path / "ttyACM0"
    emu = AdapterEmulator(link, "wacousb-e2e")
    config = parse_config(
        f"""
buses:
  robot: {{interface: wacousb, channel: "{link}", bitrate: 500000}}
units:
  - {{name: left, abh3_id: 1, broadcast: {{mask: 0x7f, rate_hz: 14}}}}
  - {{name: right, abh3_id: 3, protocol: "2023", velocity_model: motor}}
""",
        "wacousb.yaml",
    )
    stats: dict[str, float] = {}

    async def scenario() -> SimBus:
        with drives_on(config, "robot", "wacousb-e2e") as drives:
            async with Runtime(config) as rt:
                sup = rt.supervisor
                since = sup.clock()
                assert all(
                    await asyncio.gather(*(sup.wait_exchange(n, since, 3.0) for n in sup.units))
                )
                t0, sent0 = time.perf_counter(), rt.pumps["robot"].frames_sent
                for unit in ("left", "right"):
                    assert await sup.command(unit, "SERVO ON ON") == ""
                    assert await sup.command(unit, "START ON ON") == ""
                for unit, vel in (("left", "VEL 300 20"), ("right", "VEL 150 -150")):
                    assert await sup.command(unit, vel, source=present(sup, unit)) == ""
                # until both drives report (through the adapter) the speed they were given
                for _ in range(500):  # bounded: 10 s of exchanges
                    if reached(sup.unit("left").feedback, 300.0, 320.0) and reached(
                        sup.unit("right").feedback, 0.0, 150.0
                    ):
                        break
                    assert await sup.wait_exchange("left", sup.clock(), 1.0)
                else:
                    pytest.fail(f"never at speed: {sup.unit('left').feedback}")
                for _ in range(50):  # and a second more at speed
                    assert await sup.wait_exchange("right", sup.clock(), 1.0)
                pump = rt.pumps["robot"]
                stats["frames_per_s"] = (pump.frames_sent - sent0) / (time.perf_counter() - t0)
                stats["send_errors"] = pump.send_errors
                assert sup.unit("left").online and sup.unit("right").online
        assert rt.stops_confirmed, rt.stop_report
        assert isinstance(drives.machine, SimBus)
        return drives.machine

    try:
        sim = asyncio.run(scenario())
        assert emu.wait_for(lambda: emu.forwarded == len(emu.host_frames))
    finally:
        emu.close()
    assert emu.bad == [] and emu.junk == 0
    msgs = [check_host_frame(raw[1:-1]) for raw in emu.host_frames]  # raises if any is wrong
    assert all(raw[:1] == b"\x02" and raw[-1:] == b"\x03" for raw in emu.host_frames)
    assert len(msgs) > 100 and all(m.is_extended_id for m in msgs)
    commands = [m for m in msgs if m.arbitration_id == ids.dp0_command_id(1, 2)]
    decoded = [frames.decode_dp0_command(bytes(c.data), Generation.G2021) for c in commands]
    moving = [c for c in decoded if isinstance(c, frames.Dp0Command) and (c.cmd_ay or c.cmd_bx)]
    # the last one that moved (the way out's stop frames come after it)
    assert moving and (moving[-1].cmd_ay, moving[-1].cmd_bx) == (300.0, 20.0)
    # the drives themselves moved, then stopped: what the simulated drives saw
    left = sim.drives[1]
    assert left.cmd_raw == (0, 0) and left.frames_received > 50
    with capsys.disabled():
        print(
            f"\nwacousb end to end: {len(msgs)} frames through the adapter, "
            f"{stats['frames_per_s']:.0f} frames/s sent, {stats['send_errors']:.0f} send errors"
        )


def test_a_missing_adapter_fails_the_run_with_the_bus_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from abh3_supervisor.clients.cli import main

    path = tmp_path / "robot.yaml"
    path.write_text(
        f"buses:\n  robot: {{interface: wacousb, channel: {tmp_path}/ttyACM0}}\n"
        "units:\n  - {name: base}\n"
    )
    assert main(["run", str(path), "--headless", "--no-socket", "--duration", "1"]) == 1
    err = capsys.readouterr().err
    assert "bus 'robot': cannot open wacousb channel" in err and "No such file" in err
    assert "Traceback" not in err


def test_the_adapter_unplugged_and_back_under_a_running_supervisor(tmp_path: Path) -> None:
    link = tmp_path / "ttyACM0"
    emu = AdapterEmulator(link, "wacousb-replug")
    config = parse_config(
        f"""
buses:
  robot: {{interface: wacousb, channel: "{link}", options: {{reopen_interval: 0.05}}}}
units:
  - {{name: base, abh3_id: 4}}
""",
        "replug.yaml",
    )
    notices = BusNotices("robot")

    async def scenario() -> None:
        with drives_on(config, "robot", "wacousb-replug"):
            async with Runtime(config) as rt:
                sup = rt.supervisor
                sup.subscribe(notices)
                assert await sup.wait_exchange("base", sup.clock(), 3.0)
                emu.unplug()
                assert "SENDS FAILING" in await notices.next()
                # the first failing write may be the one that finds the adapter gone
                assert any(
                    why in notices.seen[-1] for why in ("not connected", "the adapter went away")
                )
                assert not await sup.wait_exchange("base", sup.clock(), 0.2)
                emu.plug()
                assert "recovered from sends failing" in await notices.next()
                assert await sup.wait_exchange("base", sup.clock(), 2.0)
        assert rt.stops_confirmed

    try:
        asyncio.run(scenario())
    finally:
        emu.close()
    assert emu.bad == [] and emu.junk == 0
