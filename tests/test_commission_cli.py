"""`abh3 commission` as a user runs it: mistakes answered at once (exit 2, no traceback),
and two short end-to-end runs in a process of their own — what only they can show: the
runtime's way out stops every drive on SIGINT mid-jog, and the report written beside a
recording agrees with the frames in it."""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import cast

import can
import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.commission import LiveBench, TerminalOperator, for_commissioning
from abh3_supervisor.commission.unit import Aborted
from abh3_supervisor.config import load_config
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.support.safe_word import DEMO_DRIVES, is_stop, last_commands

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "configs" / "commission-demo.yaml"
SHORT = ["--jog-seconds", "0.3", "--step-seconds", "0.3"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["middle"], "no unit named 'middle' (units: front, rear)"),
        (["--jog-fraction", "0.5"], "--jog-fraction 0.5 is out of bounds (allowed 0.01–0.2"),
        (["--jog-seconds", "3"], "--jog-seconds 3 is out of bounds (allowed 0.2–1 s)"),
        (["--report", "out.txt"], "--report out.txt: name the HTML file"),
    ],
)
def test_mistakes_are_named_with_exit_2(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["commission", str(DEMO), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--report", "{tmp}/missing/r.html"], "--report {tmp}/missing/r.html: cannot write"),
        (["--report", "{tmp}/r.html"], "--report {tmp}/r.html: cannot write"),
        (["--record", "{tmp}/missing/r.mcap"], "--record {tmp}/missing/r.mcap: cannot write"),
    ],
)
def test_an_unwritable_report_or_recording_is_refused_before_anything_opens(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "r.html").mkdir()  # a directory where the page would go
    argv = [a.format(tmp=tmp_path) for a in args]
    assert main(["commission", str(DEMO), "--yes", "--wheels-off-ground", *argv]) == 2
    out, err = capsys.readouterr()
    assert message.format(tmp=tmp_path) in err and "Traceback" not in err
    assert "commissioning" not in out  # no bus opened, nothing moved
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.html"]  # nothing left behind


def test_a_limit_too_low_to_jog_is_refused_before_anything_opens(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    slow = tmp_path / "slow.yaml"
    slow.write_text(DEMO.read_text().replace("limits: {velocity: 3000}", "limits: {velocity: 30}"))
    assert main(["commission", str(slow), "front", "--yes", "--wheels-off-ground"]) == 2
    out, err = capsys.readouterr()
    assert f"{slow}: units.front.limits.velocity 30 × --jog-fraction 0.05 is a jog of 1.2" in err
    assert "--jog-fraction 0.1" not in err and "commissioning" not in out
    assert main(["commission", str(slow), "front", "--jog-fraction", "0.1", "--report", "x.txt"])
    assert "--report x.txt" in capsys.readouterr().err  # 30 × 0.1 = 3 min⁻¹ is enough


def test_a_unit_named_twice_is_commissioned_once(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["commission", str(DEMO), "middle", "front", "middle"]) == 2
    assert capsys.readouterr().err.count("no unit named 'middle'") == 1


def test_units_may_follow_the_options(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["commission", str(DEMO), "--yes", "middle", "--jog-seconds", "0.5"]) == 2
    err = capsys.readouterr().err
    assert "no unit named 'middle'" in err and "unrecognized arguments" not in err


def test_enter_at_a_question_is_no_and_y_is_yes() -> None:
    consent = argparse.Namespace(wheels_off_ground=False, yes=False)
    operator = TerminalOperator(cast(LiveBench, None), consent, keys=True)

    async def answer(key: str) -> bool:
        question = asyncio.ensure_future(operator.confirm("jog motor A? [y/N]"))
        await asyncio.sleep(0)
        operator.key("x")  # not an answer: still asking
        await asyncio.sleep(0)
        assert not question.done()
        operator.key(key)
        await asyncio.sleep(0)
        assert question.done()
        return question.result()

    assert asyncio.run(answer("\r")) is False
    assert asyncio.run(answer("\n")) is False
    assert asyncio.run(answer("Y")) is True


def test_the_e_stop_key_at_a_question_ends_the_session_without_an_answer() -> None:
    class Bench:
        pressed = 0

        def estop(self) -> float:
            self.pressed += 1
            return 0.0

    bench = Bench()
    consent = argparse.Namespace(wheels_off_ground=False, yes=False)
    operator = TerminalOperator(cast(LiveBench, bench), consent, keys=True)

    async def main() -> None:
        question = asyncio.ensure_future(operator.confirm("jog motor A? [y/N]"))
        await asyncio.sleep(0)
        operator.key("e")
        await asyncio.sleep(0)
        assert question.done() and bench.pressed == 1
        with pytest.raises(Aborted, match="e-stop pressed"):
            question.result()

    asyncio.run(main())


def test_the_e_stop_key_puts_every_commanded_units_stop_frame_on_the_wire_at_once() -> None:
    """Not on the unit's next command period: the rehearsal's figure is the key's path."""
    config = for_commissioning(load_config(DEMO), ["front"])

    async def main() -> tuple[float, list[tuple[float, int, bytes]]]:
        async with Runtime(config, plugins=PluginHost(config, available={})) as rt:
            bench = LiveBench(rt, PluginHost(config, available={}), ["front"])
            rt.supervisor.apply_text("front", "START ON ON")
            await asyncio.sleep(0.1)
            before = len(bench.sent)
            t = bench.estop()
            return t, list(bench.sent[before:])  # before any await: sent by the key itself

    t, sent = asyncio.run(main())
    front = ids.dp0_command_id(1, 2) & 0x03FFFFFF
    stops = [s for s in sent if s[1] & 0x03FFFFFF == front]
    assert len(stops) == 1 and stops[0][0] >= t
    cmd = frames.decode_dp0_command(stops[0][2], flags.LAYOUT_2021.generation)
    assert isinstance(cmd, frames.Dp0Command) and not cmd.inputs & flags.LAYOUT_2021.start.both
    rear = ids.dp0_command_id(3, 2) & 0x03FFFFFF
    assert not [s for s in sent if s[1] & 0x03FFFFFF == rear]  # a monitor here: not commanded


def test_sigint_mid_jog_stops_every_drive(tmp_path: Path) -> None:
    record = tmp_path / "run.log"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "abh3_supervisor",
            "commission",
            str(DEMO),
            "front",
            "--yes",
            "--wheels-off-ground",
            "--record",
            str(record),
            "--report",
            str(tmp_path / "r.html"),
            *SHORT,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        cwd=tmp_path,
    )
    assert proc.stdout is not None
    deadline = time.monotonic() + 60
    for line in proc.stdout:
        if "jog motor A" in line:
            break
        assert time.monotonic() < deadline, "the jog never began"
    time.sleep(0.15)  # the subprocess is mid-jog: what is tested is its way out
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "unit front: stop confirmed" in out
    last = last_commands(record, DEMO_DRIVES)
    assert is_stop(last[1], flags.LAYOUT_2021)
    assert 3 not in last  # rear was not named: never commanded
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["ended"] == "stopped by SIGINT"
    assert report["units"]["front"]["stop"] == "confirmed"


def test_the_demo_report_names_the_fault_and_matches_the_recording(tmp_path: Path) -> None:
    record = tmp_path / "run.log"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "abh3_supervisor",
            "commission",
            str(DEMO),
            "rear",
            "--yes",
            "--wheels-off-ground",
            "--record",
            str(record),
            "--report",
            str(tmp_path / "r.html"),
            *SHORT,
        ],
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
        timeout=120,
        cwd=tmp_path,
    )
    assert run.returncode == 1, run.stderr  # a check failed
    assert "rear: FAIL — jog B: reversed axis B" in run.stdout
    doc = json.loads((tmp_path / "r.json").read_text())
    rear = doc["units"]["rear"]
    assert rear["stop"] == "confirmed" and rear["firmware"]
    fails = [c for c in rear["checks"] if c["verdict"] == "fail"]
    assert fails[0]["name"].startswith("reversed axis B") and "polarity" in fails[0]["fix"]
    assert is_stop(last_commands(record, DEMO_DRIVES)[3], flags.LAYOUT_2023)
    # every feedback sample of the report is a DP0 reply in the recording, in order
    replies = []
    for msg in can.LogReader(str(record)):
        if msg.arbitration_id == ids.dp0_reply_id(3, 2):
            reply = frames.decode_dp0_reply(bytes(msg.data), flags.LAYOUT_2023.generation)
            assert isinstance(reply, frames.Dp0Reply2023)
            replies.append((reply.vel_ay, reply.vel_bx))
    for trace in rear["traces"]:
        seen = list(zip(trace["feedback"]["a"], trace["feedback"]["b"], strict=True))
        n = len(seen)
        assert n > 5 and any(replies[i : i + n] == seen for i in range(len(replies) - n + 1))
    page = (tmp_path / "r.html").read_text()
    assert "<polyline" in page and "http" not in page


SILENT_MID_JOG = """
buses:
  robot:
    interface: virtual
    channel: silent-mid-jog
    bitrate: 500000
    simulate:
      time_constant_ms: 60
      faults: [{kind: silent, unit: front, at_s: 2.1, for_s: 60}]
units:
  - name: front
    abh3_id: 1
    host_id: 2
    protocol: "2021"
    velocity_model: motor
    command_rate_hz: 50
    limits: {velocity: 3000}
    geometry: {rate_num: 1.0, rate_den: 10.0, wheel: 0.15, width: 0.5, pulses_per_rev: 4096}
    broadcast: {mask: 0x1f, rate_hz: 20}
"""


def test_a_drive_gone_silent_mid_jog_gets_no_jog_a_quarter_second_after_its_last_answer(
    tmp_path: Path,
) -> None:
    """End to end, judged from the recording alone: the drive falls silent 2.1 s in (the
    identity takes about 1.45 s, so mid-way through the first 1 s jog; a slower start
    puts it earlier in the jog); no DP0 frame carries a jog setpoint later
    than 0.25 s after the drive's last reply, the last one is the safe word, and the
    report names the communication loss with its fix."""
    cfg = tmp_path / "silent.yaml"
    cfg.write_text(SILENT_MID_JOG)
    record = tmp_path / "run.log"
    run = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "commission", str(cfg), "--yes",
         "--wheels-off-ground", "--record", str(record), "--report", str(tmp_path / "r.html"),
         "--jog-seconds", "1"],
        capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 3, run.stdout + run.stderr  # silent still: the stop unconfirmed
    assert "Traceback" not in run.stderr
    gen = flags.LAYOUT_2021.generation
    replies: list[float] = []
    jogs: list[float] = []
    last: frames.Dp0Command | None = None
    for msg in can.LogReader(str(record)):
        if msg.arbitration_id == ids.dp0_reply_id(1, 2):
            replies.append(msg.timestamp)
        elif msg.arbitration_id == ids.dp0_command_id(1, 2):
            cmd = frames.decode_dp0_command(bytes(msg.data), gen)
            assert isinstance(cmd, frames.Dp0Command)
            last = cmd
            if (cmd.cmd_ay, cmd.cmd_bx) != (0.0, 0.0):
                jogs.append(msg.timestamp)
    assert jogs and jogs[0] < replies[-1], "the silence did not come mid-jog"
    assert jogs[-1] - replies[-1] <= 0.25, jogs[-1] - replies[-1]
    assert last is not None and is_stop(last, flags.LAYOUT_2021)
    assert "communication lost" in run.stdout and "termination" in run.stdout
    assert "power stage" not in run.stdout
    doc = json.loads((tmp_path / "r.json").read_text())
    names = [c["name"] for c in doc["units"]["front"]["checks"] if c["verdict"] == "fail"]
    assert names[0] == "communication lost", names
