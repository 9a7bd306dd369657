"""The ``abh3`` command end to end, in a subprocess, as a user runs it."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from tests.support.cli import abh3

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

ROOT = Path(__file__).resolve().parent.parent
DEMO = ROOT / "configs" / "demo.yaml"


def decoded(path: Path) -> list[dict[str, Any]]:
    out = abh3("decode", str(path), "--config", str(DEMO), "--json")
    assert out.returncode == 0, out.stderr
    return [json.loads(line) for line in out.stdout.splitlines()]


def test_headless_run_records_what_was_commanded_at_the_configured_rate(tmp_path: Path) -> None:
    record = tmp_path / "t.log"
    run = abh3("run", str(DEMO), "--headless", "--duration", "3", "--record", str(record))
    assert run.returncode == 0, run.stderr
    assert "unit left: online" in run.stderr and "unit right: online" in run.stderr
    rows = decoded(record)
    # --record says where at the start and how many frames at the end
    assert f"recording all bus traffic to {record.resolve()}" in run.stderr
    counted = re.search(r"recorded (\d+) frames \(\d+ sent, \d+ received\) to ", run.stderr)
    assert counted is not None and int(counted[1]) == len(rows)
    for unit, mask, commanded in (("left", 0x7F, (300.0, 20.0)), ("right", 0x0F, (150.0, -150.0))):
        mine = [r for r in rows if r.get("unit") == unit]  # transport frames name none
        cmds = [r for r in mine if r["kind"] == "dp0_command"]
        replies = [r for r in mine if r["kind"] == "dp0_reply"]
        times = [float(r["t"]) for r in cmds]
        rate = (len(times) - 2) / (times[-2] - times[0])  # the last one is the stop frame
        assert abs(rate - 50) / 50 < 0.05, rate
        assert abs(len(replies) - len(cmds)) <= 1  # every command answered
        values = Counter((r["values"]["cmd_ay"], r["values"]["cmd_bx"]) for r in cmds)
        assert values.most_common(1)[0][0] == commanded
        packets = {r["packet"] for r in mine if r["kind"] == "broadcast"}
        assert packets == {n for n in range(7) if mask >> n & 1}
        stop = cmds[-1]
        assert stop["values"]["cmd_ay"] == 0.0 and "AY_SERVO_ON" not in stop["flags"]["inputs"]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
def test_signals_stop_the_drives_and_keep_the_recording(tmp_path: Path, sig: int) -> None:
    record = tmp_path / "sig.asc"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "abh3_supervisor",
            "run",
            str(DEMO),
            "--headless",
            "--record",
            str(record),
        ],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stderr is not None
    seen = []
    for line in proc.stderr:  # event-driven: wait for both units, no sleeping
        seen.append(line)
        if sum("online" in s for s in seen) == 2:
            break
    proc.send_signal(sig)
    rest = proc.stderr.read()
    assert proc.wait(timeout=30) == 0, rest
    assert rest.count("stop frame confirmed by the drive") == 2
    assert "Traceback" not in rest
    cmds = [r for r in decoded(record) if r["kind"] == "dp0_command"]
    for unit in ("left", "right"):
        last = [r for r in cmds if r["unit"] == unit][-1]
        assert not {"AY_SERVO_ON", "AY_START", "BX_SERVO_ON", "BX_START"} & set(
            last["flags"]["inputs"]
        )


def test_check_prints_the_bus_load_plan(tmp_path: Path) -> None:
    out = abh3("check", str(DEMO), "--json")
    assert out.returncode == 0, out.stderr
    plan = json.loads(out.stdout)
    bus = plan["buses"][0]
    # per unit: 50 × 2 DP0 frames + polls × (request + reply); worst case 160/110 bits
    assert bus["frames_per_s"] == pytest.approx(2 * (50 + 14) + 2 * (50 + 8))
    worst = 50 * 320 + 14 * 270 + 50 * 320 + 8 * 270
    assert bus["worst_load_percent"] == pytest.approx(worst / 5000)
    assert 0.75 * worst < bus["bits_per_s"] < worst  # exact stuffing of idle frames
    assert bus["load_percent"] == pytest.approx(bus["bits_per_s"] / 5000)
    text = abh3("check", str(DEMO))
    assert "bus demo: 500000 bit/s" in text.stdout


def test_an_overloaded_plan_fails_check_and_run_refuses_it_with_the_same_message(
    tmp_path: Path,
) -> None:
    cfg = tmp_path / "busy.yaml"
    units = "\n".join(
        f"  - {{name: u{i}, abh3_id: {i + 10}, command_rate_hz: 500}}" for i in range(4)
    )
    cfg.write_text(
        f"buses:\n  can0: {{interface: virtual, bitrate: 250000, simulate: true}}\n"
        f"units:\n{units}\n"
    )
    message = (
        f"error: {cfg}:2: buses.can0: worst-case load 260.3 % exceeds the bus at 250000 "
        "bit/s: lower command_rate_hz or broadcast.rate_hz, or raise the bitrate\n"
    )
    check = abh3("check", str(cfg))
    assert check.returncode == 1 and "OK" not in check.stdout
    assert "bus can0: 250000 bit/s" in check.stdout and check.stderr == message
    run = abh3("run", str(cfg), "--headless", "--duration", "1")
    assert run.returncode == 1 and run.stderr == message
    as_json = json.loads(abh3("check", str(cfg), "--json").stdout)
    assert as_json["ok"] is False and as_json["errors"] == [message[7:-1]]


def test_check_json_of_a_file_it_refuses_says_so_in_json_too(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("buses:\n  can0: {interface: virtual}\nunits:\n  - {name: u, abh3_id: 900}\n")
    out = abh3("check", str(cfg), "--json")
    assert out.returncode == 2
    told = json.loads(out.stdout)
    assert (told["file"], told["ok"]) == (str(cfg), False)
    assert len(told["errors"]) == 1 and "abh3_id" in told["errors"][0]
    assert told["errors"][0] in out.stderr and "Traceback" not in out.stderr


def test_a_plan_with_little_headroom_runs_with_a_warning(tmp_path: Path) -> None:
    cfg = tmp_path / "busy.yaml"
    cfg.write_text(
        "buses:\n  slow: {interface: virtual, channel: c, bitrate: 250000, simulate: true}\n"
        "units:\n  - {name: u0, abh3_id: 10, command_rate_hz: 400, broadcast: {rate_hz: 200}}\n"
    )
    check = abh3("check", str(cfg))
    assert check.returncode == 0 and "warning: worst-case load 72.8 % is above 70 %" in check.stdout
    run = abh3("run", str(cfg), "--headless", "--duration", "0.5")
    assert run.returncode == 0 and "WARNING bus slow: worst-case load 72.8 %" in run.stderr


def test_at_most_twenty_problems_are_printed(tmp_path: Path) -> None:
    cfg = tmp_path / "many.yaml"
    units = "".join(f"  - {{name: u{i}, abh3_id: {i + 10}, priority: 9}}\n" for i in range(25))
    cfg.write_text(f"buses:\n  can0: {{}}\nunits:\n{units}")
    out = abh3("check", str(cfg))
    lines = out.stderr.splitlines()
    assert out.returncode == 2 and len(lines) == 21 and lines[-1] == "error: and 5 more"


def test_decode_without_config_uses_seed_defaults(tmp_path: Path) -> None:
    log = tmp_path / "x.log"
    log.write_text(
        "(1.000000) can0 00EF0102#F401000001100000 T\n"
        "(1.001000) can0 00EF0201#F3FF0000FAFFF9FF R\n"  # a 2021 reply: Y = (A+B)/2, X = A-Y
        "(1.002000) can0 18FEF100#0000000000000000 R\n"
    )
    out = abh3("decode", str(log))
    assert out.stderr == "decode: address 1 looks like a 2021 drive (no --config): guessed\n"
    lines = out.stdout.splitlines()
    assert "dp0_command" in lines[0] and "cmd_ay=100.0" in lines[0]
    assert "inputs[AY_SERVO_ON,BX_SERVO_ON]" in lines[0]
    assert "dp0_reply" in lines[1] and "vel_a=-2.6" in lines[1]
    assert "unknown" in lines[2] and "not ABH3" in lines[2]


def test_user_mistakes_give_messages_not_tracebacks(tmp_path: Path) -> None:
    out = abh3("decode", str(tmp_path / "missing.log"))
    assert out.returncode == 2 and "cannot read recording" in out.stderr
    assert "Traceback" not in out.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("buses:\n  can0: {}\nunits:\n  - {name: a, abh3_id: 300}\n")
    out = abh3("run", str(bad), "--headless")
    assert out.returncode == 2 and "bad.yaml:4: units[0].abh3_id: 300 is out of range" in out.stderr
    out = abh3("run", str(DEMO), "--duration", "-1")
    assert out.returncode == 2 and "must be more than 0" in out.stderr
    missing = tmp_path / "hw.yaml"
    missing.write_text("buses:\n  can0: {channel: can7}\nunits:\n  - {name: a}\n")
    out = abh3("run", str(missing), "--headless", "--duration", "1")
    assert out.returncode == 1 and "cannot open socketcan channel 'can7'" in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize("config", sorted(p.name for p in (ROOT / "configs").glob("*.yaml")))
def test_every_shipped_configuration_checks_clean(config: str) -> None:
    out = abh3("check", f"configs/{config}")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "OK" in out.stdout


# ---------------------------------------------------------------- signals while starting


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_loading_ends_at_once_and_starts_nothing(tmp_path: Path, sig: int) -> None:
    fifo = tmp_path / "config.yaml"
    os.mkfifo(fifo)
    proc = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", str(fifo), "--headless"],
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    with open(fifo, "w"):  # opens once the program reads it, its handlers in place
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 128 + sig, err
    name = signal.Signals(sig).name
    assert err == f"abh3: stopped by {name} while starting; no drive was started\n"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_while_a_recording_blocks_opening_ends_at_once_and_sends_nothing(
    tmp_path: Path, sig: int
) -> None:
    record = tmp_path / "blocked.log"
    os.mkfifo(record)  # opening it for writing blocks until someone reads: it never happens
    config = tmp_path / "busy.yaml"  # a plan warning is logged just before the runtime starts
    config.write_text(
        "buses:\n  slow: {interface: virtual, channel: c, bitrate: 250000, simulate: true}\n"
        "units:\n  - {name: u0, abh3_id: 10, command_rate_hz: 400, broadcast: {rate_hz: 200},\n"
        "     startup: ['SERVO ON ON']}\n"
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "abh3_supervisor",
            "run",
            str(config),
            "--headless",
            "--record",
            str(record),
        ],
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    assert proc.stderr is not None
    assert "worst-case load" in proc.stderr.readline()
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 128 + sig, err
    assert "Traceback" not in err and "startup" not in err and "running" not in err
