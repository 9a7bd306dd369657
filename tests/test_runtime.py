"""The asyncio runtime on python-can's virtual bus: start, record, and every way out."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import can
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import BusOpenError
from abh3_supervisor.protocol import flags
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.headless import run_headless
from abh3_supervisor.scheduler.core import BusScheduler
from tests.support.rig import TWO_UNITS, present, set_velocity
from tests.support.safe_word import commands_to, is_safe_word

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

CONFIG = parse_config(TWO_UNITS, "two.yaml")


def protocol_of(abh3_id: int) -> Generation:
    return next(u.protocol for u in CONFIG.units.values() if u.abh3_id == abh3_id)


async def until_online(rt: Runtime) -> None:
    sup = rt.supervisor
    since = sup.clock()
    results = await asyncio.gather(*(sup.wait_exchange(n, since, 2.0) for n in sup.units))
    assert all(results)


def test_runs_records_and_stops_the_drives_on_the_way_out(tmp_path: Path) -> None:
    record = tmp_path / "run.log"

    async def scenario() -> None:
        async with Runtime(CONFIG, record=record) as rt:
            await until_online(rt)
            sup = rt.supervisor
            for unit in ("left", "right"):
                assert await sup.command(unit, "SERVO ON ON") == ""
                assert await sup.command(unit, "START ON ON") == ""
            set_velocity(sup, "left", 200, 10, source=present(sup, "left"))
            assert await sup.command("left", "FOO") == "Invalid Command."
            await sup.wait_exchange("left", sup.clock(), 1.0)

    asyncio.run(scenario())
    left = commands_to(record, 1, protocol_of(1))
    assert any(c.cmd_ay == 200.0 and c.cmd_bx == 10.0 for c in left)
    for abh3_id in (1, 3):
        # the recording is complete: the stop frame
        last = commands_to(record, abh3_id, protocol_of(abh3_id))[-1]
        assert (last.cmd_ay, last.cmd_bx) == (0.0, 0.0)
        assert is_safe_word(last.inputs, flags.layout(protocol_of(abh3_id)))


def test_an_exception_in_the_block_still_stops_the_drives(tmp_path: Path) -> None:
    record = tmp_path / "crash.log"

    async def scenario() -> None:
        async with Runtime(CONFIG, record=record) as rt:
            await until_online(rt)
            rt.supervisor.apply_text("left", "SERVO ON ON")
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        asyncio.run(scenario())
    assert is_safe_word(commands_to(record, 1, protocol_of(1))[-1].inputs, flags.LAYOUT_2021)


def test_a_fatal_internal_error_ends_the_run_with_exit_1_after_stopping(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    record = tmp_path / "fatal.log"
    calls = {"n": 0}
    real = BusScheduler.on_frame

    def on_frame(self: BusScheduler, arbitration_id: int, data: bytes, now: float) -> None:
        calls["n"] += 1
        if calls["n"] == 50:
            raise ZeroDivisionError("bug")
        real(self, arbitration_id, data, now)

    monkeypatch.setattr(BusScheduler, "on_frame", on_frame)
    with caplog.at_level(logging.INFO):
        code = asyncio.run(run_headless(CONFIG, duration=30, record=record, status_interval=0))
    assert code == 1
    assert "stopping after an internal error" in caplog.text
    assert is_safe_word(commands_to(record, 3, protocol_of(3))[-1].inputs, flags.LAYOUT_2023)


def test_a_missing_device_is_a_clear_error() -> None:
    cfg = parse_config("buses: {can9: {channel: can9}}\nunits: [{name: u}]\n", "r.yaml")

    async def scenario() -> None:
        async with Runtime(cfg):
            pass

    with pytest.raises(BusOpenError, match="bus 'can9': cannot open socketcan channel 'can9'"):
        asyncio.run(scenario())


def test_an_unknown_recording_format_is_a_clear_error(tmp_path: Path) -> None:
    async def scenario() -> None:
        async with Runtime(CONFIG, record=tmp_path / "x.unknown"):
            pass

    with pytest.raises(
        BusOpenError, match=r"--record .*x.unknown.*use \.log .*\.asc .*\.blf .*\.csv"
    ):
        asyncio.run(scenario())


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".csv"])
def test_every_recording_format_is_readable_again(tmp_path: Path, suffix: str) -> None:
    record = tmp_path / f"run{suffix}"

    async def scenario() -> None:
        async with Runtime(CONFIG, record=record) as rt:
            await until_online(rt)

    asyncio.run(scenario())
    assert len(commands_to(record, 1, protocol_of(1))) >= 2


def test_packet_errors_for_no_reply_and_refused_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = parse_config(TWO_UNITS.replace("name: left,", "name: left, timeout_ms: 200,"), "t.yaml")

    async def scenario() -> None:
        async with Runtime(cfg) as rt:
            await until_online(rt)
            rt.sims["b"].drives[1].silent = True
            assert await rt.supervisor.command("left", "SERVO ON ON") == "Packet Error: 1"
            rt.sims["b"].drives[1].silent = False
            bus = rt.pumps["b"].bus

            def refuse(msg: can.Message, timeout: float | None = None) -> None:
                raise can.CanOperationError("Transmit buffer full")

            monkeypatch.setattr(bus, "send", refuse)
            assert await rt.supervisor.command("left", "SERVO ON ON") == "Packet Error: 2"
            monkeypatch.undo()

    asyncio.run(scenario())
