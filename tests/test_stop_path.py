"""The stop path under faults, on the virtual bus: what the simulated drives end up doing."""

from __future__ import annotations

import asyncio
import errno
import logging
from pathlib import Path

import can
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.stopping import CONFIRMED, SENT
from abh3_supervisor.simulator.drive import SimDrive
from tests.support.rig import TWO_UNITS
from tests.support.safe_word import assert_drive_stopped

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

CONFIG = parse_config(TWO_UNITS, "two.yaml")


async def moving(rt: Runtime) -> None:
    sup = rt.supervisor
    since = sup.clock()
    assert all(await asyncio.gather(*(sup.wait_exchange(n, since, 2.0) for n in sup.units)))
    for unit in sup.units:
        for text in ("SERVO ON ON", "START ON ON", "BRAKE ON ON", "DIR ON ON", "VEL 100 100"):
            assert await sup.command(unit, text) == ""


def drives(rt: Runtime) -> list[SimDrive]:
    return list(rt.sims["b"].drives.values())


class FailingWriter(can.Listener):
    def __init__(self) -> None:
        self.failing = False
        self.written = 0

    def on_message_received(self, msg: can.Message) -> None:
        if self.failing:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.written += 1

    def stop(self) -> None:
        if self.failing:
            raise OSError(errno.ENOSPC, "No space left on device")


def test_a_recorder_failing_at_the_stop_does_not_keep_a_drive_running(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    writer = FailingWriter()
    rt = Runtime(CONFIG, record=tmp_path / "r.log")

    async def scenario() -> None:
        async with rt:
            assert rt._recorder is not None
            rt._recorder.writer = writer  # the disk fills up just as we stop
            await moving(rt)
            writer.failing = True

    with caplog.at_level(logging.INFO):
        asyncio.run(scenario())
    assert writer.written > 0
    assert rt.stop_report == {"left": CONFIRMED, "right": CONFIRMED}
    for drive in drives(rt):
        assert_drive_stopped(drive)  # brake, direction: everything off, not only SERVO and START
    assert caplog.text.count("writing failed") == 1  # once, not per frame
    assert "Traceback" not in caplog.text


def test_a_bus_refusing_the_stop_is_reported_and_retried(
    caplog: pytest.LogCaptureFixture,
) -> None:
    rt = Runtime(CONFIG)
    refused = {"left": 0}

    async def scenario() -> None:
        async with rt:
            await moving(rt)
            pump = rt.pumps["b"]
            real = pump.bus.send
            loop = asyncio.get_running_loop()
            until = loop.time() + 0.2  # the first 0.2 s of the stop: refused

            def send(msg: can.Message, timeout: float | None = None) -> None:
                if loop.time() < until and msg.arbitration_id & 0xFF00 == 0x0100:
                    refused["left"] += 1
                    raise can.CanOperationError("Transmit buffer full")
                real(msg, timeout)

            pump.bus.send = send  # type: ignore[method-assign]

    with caplog.at_level(logging.INFO):
        asyncio.run(scenario())
    assert refused["left"] > 1  # retried while refused …
    assert rt.stop_report == {"left": CONFIRMED, "right": CONFIRMED}  # … until it went out
    for drive in drives(rt):
        assert_drive_stopped(drive)


@pytest.mark.wire_allow(
    "safe_exit", reason="the bus refuses every frame to left: its stop cannot go out"
)
def test_stops_that_cannot_be_confirmed_say_so_per_unit() -> None:
    rt = Runtime(CONFIG)

    async def scenario() -> None:
        async with rt:
            await moving(rt)
            rt.sims["b"].drives[3].silent = True  # right: hears, never answers
            pump = rt.pumps["b"]
            real = pump.bus.send

            def send(msg: can.Message, timeout: float | None = None) -> None:
                if msg.arbitration_id & 0xFF00 == 0x0100:  # left: every frame refused
                    raise can.CanOperationError("Transmit buffer full")
                real(msg, timeout)

            pump.bus.send = send  # type: ignore[method-assign]

    asyncio.run(scenario())
    assert rt.stop_report == {"left": "NOT sent: Transmit buffer full", "right": SENT}
    assert not rt.stops_confirmed
    assert_drive_stopped(rt.sims["b"].drives[3])  # it heard the stop, though it did not answer
    left = rt.sims["b"].drives[1]
    assert left.inputs & left.layout.start.both  # never heard: only its own timeout stops it


def test_a_late_reply_to_an_earlier_command_does_not_confirm_the_stop() -> None:
    """A slow drive answers a command sent before the stop after the stop frame went out:
    that reply shows the drive still running, so it confirms nothing."""
    rt = Runtime(CONFIG)

    async def scenario() -> None:
        async with rt:
            await moving(rt)
            for drive in drives(rt):
                drive.extra_delay = 0.5  # replies come late from now on
            stats = rt.supervisor.schedulers["b"].slots["left"].stats
            sent = stats.commands_sent
            while stats.commands_sent < sent + 3:  # commands go out whose late replies
                await asyncio.sleep(0.01)  # will arrive during the stop
            for drive in drives(rt):
                drive.extra_delay = 2.0  # and the stop frames' replies after the deadline

    asyncio.run(scenario())
    # within the 1 s deadline only replies to commands before the stop arrive, reporting
    # the drives still running: not confirmed (before, any reply counted)
    assert rt.stop_report == {"left": SENT, "right": SENT}
    for drive in drives(rt):
        assert_drive_stopped(drive)  # though the drives did take the stop
