"""The stop path under faults, on the virtual bus: what the simulated drives end up doing."""

from __future__ import annotations

import asyncio
import errno
import logging
from pathlib import Path

import can
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.protocol.frames import Generation
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


def test_the_normal_way_out_is_a_controlled_stop_judged_on_the_recorded_frames(
    tmp_path: Path,
) -> None:
    """Stop category 1 (docs/safety.md): zero and START off in the first stop frame with
    SERVO kept while the drive ramps down; SERVO and brake release off only after the drive
    reported standing; the last frame the safe word."""
    path = tmp_path / "way-out.log"
    rt = Runtime(CONFIG, record=path)

    async def scenario() -> None:
        async with rt:
            await moving(rt)
            await asyncio.sleep(0.3)  # at speed

    asyncio.run(scenario())
    assert rt.stops_confirmed
    cfg = CONFIG.units["left"]  # 2021, travel model
    lay = rt.supervisor.units["left"].layout
    command = ids.dp0_command_id(cfg.abh3_id, cfg.host_id) & ids.MATCH_MASK
    reply = ids.dp0_reply_id(cfg.abh3_id, cfg.host_id) & ids.MATCH_MASK
    commands: list[tuple[int, int, int, int]] = []  # (position, AY, BX, word)
    replies: list[tuple[int, float]] = []  # (position, the faster axis's speed)
    for i, msg in enumerate(can.LogReader(str(path))):
        key = msg.arbitration_id & ids.MATCH_MASK
        if key == command:
            commands.append((i, *frames.unpack_dp0_command(bytes(msg.data))))
        elif key == reply:
            r = frames.decode_dp0_reply(bytes(msg.data), Generation.G2021)
            assert isinstance(r, frames.Dp0Reply2021)
            replies.append((i, max(abs(r.vel_a), abs(r.vel_b))))
    last_moving = max(i for i, ay, bx, _ in commands if ay or bx)
    stop = [c for c in commands if c[0] > last_moving]
    first, ay, bx, word = stop[0]
    assert (ay, bx) == (0, 0) and not word & lay.start.both
    assert word & lay.servo.both == lay.servo.both  # SERVO kept: the drive ramps down
    off = next(i for i, _, _, w in stop if not w & lay.servo.both)
    between = [speed for i, speed in replies if first < i < off]
    assert between and between[-1] < 2.0  # it reported standing before SERVO went off
    assert between[0] > 2.0  # and was still moving when the stop began
    last = stop[-1][3]
    assert last == lay.safe(last) and not last & lay.brake_release
