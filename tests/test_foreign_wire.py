"""A second host on the wire, in real time: a supervisor on the simulator (python-can's
virtual bus) and a hand-made foreign host — a second ``can.Bus`` on the same channel,
commanding the drive with our own host address, as a second copy of us would — judged
from a third listener's frames; and the tools that must refuse such a bus (commission,
param -c: test_param_cli.py) or report it (scan --listen-only)."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import can
import pytest

from abh3_supervisor.clients import control
from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.clients.scan import Findings
from abh3_supervisor.config import parse_config
from abh3_supervisor.core import commands
from abh3_supervisor.core.diagnostics import Health, Level
from abh3_supervisor.core.eventlog import EventLog
from abh3_supervisor.core.foreign import QUIET_S
from abh3_supervisor.core.supervisor import Notice, SupervisorEvent
from abh3_supervisor.errors import CommandError, RunError
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.snapshot import supervisor_state
from tests.support.foreign_host import BusHost, moving_word, safe_word
from tests.support.rig import set_velocity
from tests.support.safe_word import assert_drive_stopped, is_safe_word
from tests.support.served import Served

pytestmark = pytest.mark.wallclock  # real time: runtimes and buses

# 10 Hz: a unit's next period may be 100 ms away, so only the stop sent at once is in time
SLOW = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: true}}
units:
  - {{name: left, abh3_id: 1, command_rate_hz: 10, drive_timeout_ms: 300,
     startup: ['SERVO ON ON', 'START ON ON', 'VEL 100 100']}}
  - {{name: right, abh3_id: 3, protocol: "2023", command_rate_hz: 10, drive_timeout_ms: 300,
     startup: ['SERVO ON ON']}}
"""
OURS = ids.dp0_command_id(1, 2)


def safe(data: bytes) -> bool:
    ay, bx, inputs = frames.unpack_dp0_command(data)
    return ay == bx == 0 and is_safe_word(inputs, flags.LAYOUT_2021)


class Listener:
    """A third node on the channel: every frame, with the virtual bus's send time."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames: list[tuple[float, int, bytes]] = []

    def drain(self) -> list[tuple[float, int, bytes]]:
        while (msg := self.bus.recv(0)) is not None:
            self.frames.append((msg.timestamp, msg.arbitration_id, bytes(msg.data)))
        return self.frames


async def until(condition: object, timeout: float = 5.0) -> None:
    """Wait (on the loop, in small steps) until ``condition()`` holds."""
    deadline = time.monotonic() + timeout
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out waiting"
        await asyncio.sleep(0.005)


def test_a_second_host_is_stopped_at_once_kept_stopped_and_named(
    caplog: pytest.LogCaptureFixture,
) -> None:
    config = parse_config(SLOW.format(channel="foreign-e2e"), "slow.yaml")
    listener = Listener("foreign-e2e")
    notices: list[Notice] = []

    async def scenario() -> dict[str, object]:
        async with Runtime(config) as rt:
            sup, sim = rt.supervisor, rt.sims["b"]
            log = EventLog(sup)  # the log `abh3 run` writes (headless and served)

            def logged(event: SupervisorEvent) -> None:
                if isinstance(event, Notice):
                    notices.append(event)
                    if (line := log.line(event)) is not None:
                        logging.getLogger("abh3.events").log(*line)

            sup.subscribe(logged)
            await until(lambda: sim.drives[1].cmd_raw == (500, 500))  # left moves
            word = moving_word(rpm=200)  # not ours: told apart on the wire by its payload
            host = BusHost("foreign-e2e", 1, word=word)
            hosting = asyncio.ensure_future(host.run())
            await until(lambda: "left" in sup.gate.foreign)
            # the host goes on commanding for 8 more of our periods: we must stay stopped
            stats = sup.schedulers["b"].slots["left"].stats
            sent = stats.commands_sent
            await until(lambda: stats.commands_sent >= sent + 8)
            with pytest.raises(CommandError, match=r"another host \(0x02\) commands drive 0x01"):
                set_velocity(sup, "left", 10, 10)
            assert sup.apply_text("left", "SERVO ON ON") == commands.RESPONSE_INVALID
            assert sup.clear_emergency_stop("test")  # not while it is heard
            state = supervisor_state(sup, rt.pumps)["units"]
            diagnostics = {s.name: s for s in Health(sup).statuses(sup.clock())}
            host.leave()
            await hosting
            gone = sup.clock()
            await until(lambda: sup.clock() - gone > QUIET_S + 0.05, QUIET_S + 2)
            # the host gone, the drive is left with our safe word: stopped, servo off
            assert_drive_stopped(sim.drives[1])
            assert not sim.drives[1].control_word() & flags.LAYOUT_2021.servo.both
            standing = sup.clear_emergency_stop("test")
            right = sim.drives[3].inputs
            return {
                "host": host,
                "state": state,
                "diagnostics": diagnostics,
                "standing": standing,
                "cleared": dict(sup.gate.foreign),
                "right": right,
            }

    try:
        with caplog.at_level(logging.WARNING):
            got = asyncio.run(scenario())
        wire = listener.drain()
    finally:
        listener.bus.shutdown()
    host = got["host"]
    assert isinstance(host, BusHost) and host.first is not None and host.count > 20
    theirs = moving_word(rpm=200)
    foreign = [t for t, i, d in wire if i == OURS and d == theirs]
    first, last = foreign[0], foreign[-1]
    # ours while the host commanded: the safe word, the first within 100 ms of its first
    ours = [(t, d) for t, i, d in wire if i == OURS and d != theirs and first <= t <= last]
    assert ours[0][0] - first < 0.1, ours[0][0] - first
    assert len(ours) >= 8 and all(safe(d) for _, d in ours)
    # right, a robot of its own, was not stopped: its SERVO stayed on
    assert isinstance(got["right"], int) and got["right"] & 0x0101
    # status, diagnostics and the log name the host
    state = got["state"]["left"]["foreign"]  # type: ignore[index]
    assert "another host (0x02) commands drive 0x01" in state["stopped"]
    assert state["hosts"][0]["source"] == 2 and state["hosts"][0]["frames"][0]["count"] > 10
    status = got["diagnostics"]["abh3_supervisor: unit left"]  # type: ignore[index]
    assert status.level is Level.ERROR and "0x02" in status.message
    assert ("foreign host", "0x02") in status.values
    # the detection is said once, however many frames came (the rest: the test's own acts)
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "another host (0x02) commands drive 0x01" in errors[0].message
    assert "× DP0 command (last 00EF0102 [e8 03 e8 03 03 30 00 00])" in errors[0].getMessage()
    # cleared once the host had been quiet; nothing came back by itself
    assert got["standing"] == [] and got["cleared"] == {}


# ------------------------------------------------------------ the tools


def test_scan_findings_name_each_host_commanding_a_drive() -> None:
    f = Findings(host=2)
    f.observe(ids.broadcast_id(1, 5, 0), bytes(8))  # drive 1 is known
    for _ in range(5):
        f.observe(ids.dp0_command_id(1, 9), moving_word())
    f.observe(ids.CanId(7, ids.PF_TP_CM, 1, 9).to_int(), bytes([0x10, 20, 0, 3, 0xFF, 0, 0xEF, 0]))
    f.observe(
        ids.CanId(7, ids.PF_TP_CM, 9, 1).to_int(), bytes([0x11, 3, 1, 0xFF, 0xFF, 0, 0xEF, 0])
    )
    f.observe(ids.request_id(1, 4), frames.encode_request(frames.PGN_DP0))  # a reader
    f.finish()
    assert f.commanding() == [
        "host 9 commands drive 1: 5 × DP0 command, 1 × parameter session (TP)"
    ]


def test_scan_listen_only_reports_the_supervisor_commanding_its_drives(
    capsys: pytest.CaptureFixture[str],
) -> None:
    config = parse_config(SLOW.format(channel="foreign-scan"), "slow.yaml")

    async def scenario() -> int:
        async with Runtime(config) as rt:
            await rt.supervisor.wait_exchange("left", rt.supervisor.clock(), 2.0)
            argv = ["scan", "--interface", "virtual", "--channel", "foreign-scan"]
            return await asyncio.to_thread(main, [*argv, "--listen-only", "--listen", "0.5"])

    assert asyncio.run(scenario()) == 0
    out = capsys.readouterr().out
    assert "hosts commanding drives" in out
    lines = [line.strip() for line in out.splitlines()]
    assert any(
        line.startswith("host 2 commands drive 1: ") and "× DP0 command" in line for line in lines
    )
    assert any(line.startswith("host 2 commands drive 3: ") for line in lines)


def test_commission_refuses_a_bus_where_another_host_commands_the_drive(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    demo = Path(__file__).resolve().parent.parent / "configs" / "commission-demo.yaml"
    text = demo.read_text().replace("channel: commission-demo", "channel: foreign-commission")
    text = text.replace(
        "    command_rate_hz: 50\n", "    command_rate_hz: 50\n    drive_timeout_ms: 200\n"
    )
    path = tmp_path / "c.yaml"
    path.write_text(text)
    service = parse_config(SLOW.format(channel="foreign-commission"), "s.yaml")

    async def scenario() -> int:
        async with Runtime(service) as rt:
            await rt.supervisor.wait_exchange("left", rt.supervisor.clock(), 2.0)
            argv = ["commission", str(path), "front", "--yes", "--wheels-off-ground"]
            code = await asyncio.to_thread(main, argv)
            assert not rt.supervisor.gate.foreign  # nothing of the tool's reached the bus
            return code

    assert asyncio.run(scenario()) == 2
    err = capsys.readouterr().err
    assert "abh3 commission: refused: another host already commands a drive" in err
    assert "another host (0x02) commands drive 0x01 (unit front)" in err
    assert "heard in 0.30 s of listening" in err and "Traceback" not in err


def test_the_socket_names_the_host_to_the_client_that_lost_its_motion(served: Served) -> None:
    """A client holding motion is told it was lost to another host; `state` carries the
    host; `clear_estop` (and `abh3 estop --clear`) say the stop stands while it is heard."""
    setup = ControlClient(served.path)
    holder = ControlClient(served.path)
    foreign = can.Bus(interface="virtual", channel="t")  # TWO_UNITS' channel
    try:
        for text in ("SERVO ON ON", "START ON ON"):
            assert setup.call("command", unit="left", text=text)["response"] == ""
        assert holder.call("command", unit="left", text="VEL 100 0")["held"]
        for data in (moving_word(), safe_word()):  # one command, then it leaves politely
            foreign.send(can.Message(arbitration_id=OURS, data=data, is_extended_id=True))
        why = "stopped: another host (0x02) commands drive 0x01 (unit left)"
        deadline = time.monotonic() + 5.0
        while (reply := holder.call("alive"))["holds"]:
            assert time.monotonic() < deadline, "the motion was not dropped"
        assert reply["lost"] == {"left": why}
        state = setup.call("state")["units"]["left"]["foreign"]
        assert state["stopped"] == "another host (0x02) commands drive 0x01 (unit left)"
        assert state["hosts"][0]["frames"][0]["count"] == 2
        answer = setup.call("clear_estop")
        assert answer["ok"] and "heard" in answer["standing"][0]
        with pytest.raises(RunError, match="not every stop: unit 'left': another host"):
            control.estop(served.path, clear=True)
    finally:
        foreign.shutdown()
        holder.close()
        setup.close()
