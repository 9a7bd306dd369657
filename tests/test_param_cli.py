"""`abh3 param` on simulated drives over python-can's virtual bus (hermetic, no sleeps of
ours: each command runs until its exchanges end)."""

from __future__ import annotations

import asyncio
import csv
import json
import logging
from pathlib import Path

import pytest
import yaml

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime

SIM = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: {simulate}}}
units:
  - {{name: left, abh3_id: 1{extra}}}
  - {{name: right, abh3_id: 3, protocol: "2023"}}
"""


async def started(rt: Runtime) -> None:
    """Once a service's start-up check has read its drives: a tool with the same host
    address starting a transfer meanwhile would find the drive busy (docs/parameters.md)."""
    if rt.verifying is not None:
        await asyncio.wait_for(asyncio.shield(rt.verifying), 5)


def config(tmp_path: Path, channel: str, simulate: str = "true", extra: str = "") -> Path:
    path = tmp_path / f"{channel}.yaml"
    path.write_text(SIM.format(channel=channel, simulate=simulate, extra=extra))
    return path


@pytest.mark.wallclock
def test_get_identity_and_a_refused_address(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = str(config(tmp_path, "p-get"))
    assert main(["param", "-c", cfg, "get", "left", "SPEED_AY_0", "0x4117", "16663"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["0x5000", "SPEED_AY_0", "800", "(00400008)"]
    # the simulated drive is set up as the file says: drive_timeout_ms (default 500)
    assert out[1].split()[:3] == ["0x4117", "CAN_COMMAND_ZERO_TIMEOUT", "500"]
    assert out[2] == out[1]  # 16663 is 0x4117 in decimal, as in the maker's CSV
    assert main(["param", "-c", cfg, "identity", "left"]) == 0
    assert "FIRMWARE_VERSION   2.3.0.1" in capsys.readouterr().out
    assert main(["param", "-c", cfg, "get", "left", "0x1234"]) == 1
    assert "0x1234: the drive refused it (NAK)" in capsys.readouterr().err
    assert main(["param", "-c", cfg, "get", "left", "NOT_A_NAME"]) == 2
    assert main(["param", "-c", cfg, "get", "nobody", "0x5000"]) == 2


@pytest.mark.wallclock
def test_monitor_reads_the_simulated_state(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = str(config(tmp_path, "p-mon"))
    assert (
        main(
            [
                "param",
                "-c",
                cfg,
                "monitor",
                "right",
                "VELOCITY_AY",
                "MAIN_VOLTAGE",
                "0x0000",
                "--count",
                "2",
                "--interval",
                "0.01",
            ]
        )
        == 0
    )
    lines = capsys.readouterr().out.splitlines()
    # bit 22, CAN communication: the tool only monitors, and the drive has had no command
    assert lines == [f"VELOCITY_AY=0 MAIN_VOLTAGE=23.7 ALARMS={1 << 22}"] * 2


@pytest.mark.wallclock
def test_dump_formats(tmp_path: Path) -> None:
    # a drive taking any host (−1), unlike the file's host_id: simulate.params
    cfg = str(config(tmp_path, "p-dump", "{params: {left: {CAN_HOST_ADDRESS: -1}}}"))
    for name in ("d.csv", "d.yaml", "d.json"):
        assert main(["param", "-c", cfg, "dump", "left", "-o", str(tmp_path / name)]) == 0
    rows = list(csv.reader((tmp_path / "d.csv").read_bytes().decode("cp932").splitlines()))
    assert ["20480", "SPEED_AY_0", "800", str(0x00400008)] in rows  # decimal address first
    assert ["16643", "CAN_HOST_ADDRESS", "-1", str(0x001FFFFF)] in rows  # mantissa −1
    doc = yaml.safe_load((tmp_path / "d.yaml").read_text())
    assert doc["parameters"][0] == {
        "address": "0x4100",
        "name": "CAN_FUNCTION",
        "value": "2",
        "word": "0x00000002",
    }
    assert json.loads((tmp_path / "d.json").read_text()) == doc
    assert len(rows) == len(doc["parameters"]) == 121


@pytest.mark.wallclock
def test_diff_and_restore_write_only_what_differs_and_log_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    cfg = str(config(tmp_path, "p-restore"))
    saved = tmp_path / "saved.csv"
    assert main(["param", "-c", cfg, "dump", "left", "-o", str(saved)]) == 0
    text = saved.read_bytes().decode("cp932")
    text = text.replace("20480,SPEED_AY_0,800,4194312", "20480,SPEED_AY_0,900,4194313")
    text = text.replace(
        "16663,CAN_COMMAND_ZERO_TIMEOUT,500,4194309", "16663,CAN_COMMAND_ZERO_TIMEOUT,750,"
    )
    saved.write_bytes(
        ("address,name,display,internal\r\n" + text).encode("cp932")
    )  # a header row is fine
    capsys.readouterr()
    assert main(["param", "-c", cfg, "diff", "left", str(saved)]) == 0
    out = capsys.readouterr().out
    assert "2 parameter(s) of left differ" in out
    assert "SPEED_AY_0" in out and "CAN_COMMAND_ZERO_TIMEOUT" in out
    with caplog.at_level(logging.INFO, logger="abh3"):
        assert main(["param", "-c", cfg, "restore", "left", str(saved), "--yes"]) == 0
    out = capsys.readouterr().out
    assert "2 parameter(s) of left restored" in out
    writes = [r.getMessage() for r in caplog.records if "operator (param)" in r.getMessage()]
    assert writes == [
        "operator (param) on left: parameter 0x4117 CAN_COMMAND_ZERO_TIMEOUT: 500 (00400005) → 750 (0020004B)",
        "operator (param) on left: parameter 0x5000 SPEED_AY_0: 800 (00400008) → 900 (00400009)",
    ]


@pytest.mark.wallclock
def test_set_needs_a_confirmation_off_a_terminal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = str(config(tmp_path, "p-confirm"))
    assert main(["param", "-c", cfg, "set", "left", "SPEED_AY_0", "900"]) == 2
    assert "confirm with --yes" in capsys.readouterr().err
    assert main(["param", "-c", cfg, "set", "left", "SPEED_AY_0", "800", "--yes"]) == 0
    assert "already set: nothing written" in capsys.readouterr().out


@pytest.mark.wallclock
def test_a_bus_a_running_service_commands_is_refused_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A supervisor runs the drives (servo on); `abh3 param -c` on the same bus listens
    first, hears it command the drive and refuses (exit 2) before sending anything — so
    the service, which would take a parameter session for another host's, runs on.
    (Through the service, `--connect`, is the way: test_through_the_service.)"""
    service = parse_config(
        SIM.format(
            channel="p-servo",
            simulate="true",
            extra=", drive_timeout_ms: 200, startup: ['SERVO ON ON']",
        ),
        "s.yaml",
    )
    tool = str(config(tmp_path, "p-servo", simulate="false", extra=", drive_timeout_ms: 200"))

    async def scenario() -> list[int]:
        async with Runtime(service) as rt:
            await started(rt)  # its start-up check of the drives is done (core/verify.py)
            await rt.supervisor.wait_exchange("left", rt.supervisor.clock(), 2.0)
            codes = [
                await asyncio.to_thread(main, ["param", "-c", tool, *argv])
                for argv in (
                    ["set", "left", "SPEED_AY_0", "900", "--yes", "--force"],
                    ["get", "left", "SPEED_AY_0"],
                )
            ]
            assert rt.sims["b"].drives[1].tel.params[0x5000] == 0x00400008  # untouched
            assert not rt.supervisor.gate.foreign  # nothing of the tool's reached the bus
            return codes

    assert asyncio.run(scenario()) == [2, 2]
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "abh3 param: refused: another host already commands a drive" in captured.err
    assert "another host (0x02) commands drive 0x01 (unit left):" in captured.err
    assert "× DP0 command (last 00EF0102 [" in captured.err
    assert "heard in 0.30 s of listening, nothing sent" in captured.err
    assert "Traceback" not in captured.err


@pytest.mark.wallclock
def test_a_transport_fault_is_a_clear_error_not_a_hang(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "f.yaml"
    path.write_text(
        SIM.format(
            channel="p-fault",
            simulate="{faults: [{kind: tp_lost_cts, at_s: 0, for_s: 60}]}",
            extra="",
        )
    )
    assert main(["param", "-c", str(path), "get", "left", "0x5000"]) == 1
    assert (
        "error: unit left: CP SPEED_AY_0: no CTS from the drive within 1.25 s"
        in capsys.readouterr().err
    )


@pytest.mark.wallclock
@pytest.mark.wire_allow(
    "servo_write", reason="`param set --force` writes with the servo on, as the user asked"
)
def test_through_the_service(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`abh3 param --connect` asks the running supervisor: it refuses a write while the
    servo is on, writes with --force, and logs the write in *its* event log."""
    from abh3_supervisor.core.eventlog import EventLog
    from abh3_supervisor.core.supervisor import OperatorAction, SupervisorEvent
    from abh3_supervisor.service.server import ControlServer

    service = parse_config(
        SIM.format(channel="p-svc", simulate="true", extra=", startup: ['SERVO ON ON']"), "s.yaml"
    )
    sock = tmp_path / "s.sock"
    logged: list[str] = []

    async def scenario() -> list[int]:
        async with Runtime(service) as rt:
            await started(rt)  # its start-up check of the drives is done (core/verify.py)
            events = EventLog(rt.supervisor)

            def on_event(event: SupervisorEvent) -> None:
                if isinstance(event, OperatorAction) and (line := events.line(event)):
                    logged.append(line[1])

            rt.supervisor.subscribe(on_event)
            left = rt.supervisor.units["left"]
            for _ in range(200):  # the startup's SERVO ON, as the drive reports it (bounded)
                if left.words.get("control", 0) & left.layout.servo.both:
                    break
                await rt.supervisor.wait_exchange("left", rt.supervisor.clock(), 1.0)
            else:
                pytest.fail("the drive never reported its servo on")
            server = ControlServer(rt, None, sock)
            await server.start()
            try:
                codes = []
                for argv in (
                    ["get", "left", "SPEED_AY_0"],
                    ["set", "left", "SPEED_AY_0", "900", "--yes"],
                    ["set", "left", "SPEED_AY_0", "900", "--yes", "--force"],
                    ["identity", "right"],
                    ["get", "left", "0x1234"],
                ):
                    codes.append(
                        await asyncio.to_thread(main, ["param", "--connect", str(sock), *argv])
                    )
                return codes
            finally:
                await server.close()

    # --force skips asking the drive, never the lock: this supervisor commands SERVO ON
    assert asyncio.run(scenario()) == [0, 1, 1, 0, 1]
    out, err = capsys.readouterr()
    assert "unit left: this supervisor commands its servo ON (switch it off first)" in err
    # the refusal without --force points at SERVO OFF, not at a --force that cannot help
    assert "SERVO OFF first; --force writes with the servo on, but never while this" in err
    assert "the drive refused it (NAK)" in err
    assert "written:" not in out and "FIRMWARE_VERSION   2.3.0.1" in out
    assert logged == []  # nothing was written


def test_parameter_files_read_back_and_refuse_with_file_and_row(tmp_path: Path) -> None:
    from abh3_supervisor.params import files
    from abh3_supervisor.params.files import ParamFileError, ParamValue

    values = [ParamValue(0x5000, 0x00400008), ParamValue(0x4103, 0x001FFFFF), ParamValue(0x7777, 5)]
    for name in ("v.csv", "v.yaml", "v.json"):
        files.write(tmp_path / name, values, "left")
        assert files.read(tmp_path / name) == values
    # decimal address, name (hex for an unnamed address), display value, internal value
    assert (tmp_path / "v.csv").read_bytes().decode("cp932").splitlines() == [
        "20480,SPEED_AY_0,800,4194312",
        "16643,CAN_HOST_ADDRESS,-1,2097151",
        "30583,0x7777,5,5",
    ]
    only_display = tmp_path / "d.csv"
    only_display.write_bytes("20480,速度,900,\r\n".encode("cp932"))  # a Japanese name, no word
    assert files.read(only_display) == [ParamValue(0x5000, 0x00400009)]
    bad = tmp_path / "b.csv"
    bad.write_bytes(b"20480,SPEED_AY_0,800,4194312\r\nnonsense,x,1,2\r\n")
    with pytest.raises(ParamFileError, match=r"b.csv:2: 'nonsense' is no address"):
        files.read(bad)
    with pytest.raises(ParamFileError, match=r"use .csv"):
        files.read(tmp_path / "v.txt")
    with pytest.raises(ParamFileError, match="cannot read"):
        files.read(tmp_path / "missing.csv")


@pytest.mark.wallclock
def test_mistakes_in_files_and_values_are_named_not_dropped_or_a_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from abh3_supervisor.errors import CodecError
    from abh3_supervisor.params import files, table
    from abh3_supervisor.params.files import ParamFileError

    typo = tmp_path / "typo.yaml"  # YAML has no header row: a bad first entry is an error
    typo.write_text("parameters:\n  - {address: SPEED_AX_0, value: 800}\n")
    with pytest.raises(ParamFileError, match=r"typo.yaml:1: 'SPEED_AX_0' is no address"):
        files.read(typo)
    for value in (float("nan"), float("inf")):
        with pytest.raises(CodecError, match="is not a 32-bit integer"):
            table.to_word(value, "int")
    with pytest.raises(CodecError, match="NaN and infinities are refused"):  # issue 22
        table.to_word(float("inf"), "pf")  # a packed float has a code for it; no setting wants it
    for bad in (["--interval", "nan"], ["--count", "-1"]):
        with pytest.raises(SystemExit) as ended:
            main(["param", "-c", "configs/demo.yaml", "monitor", "left", "0x1012", *bad])
        assert ended.value.code == 2
    assert "argument --interval: must be more than 0" in capsys.readouterr().err
