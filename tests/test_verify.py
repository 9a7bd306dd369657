"""The drive and the file agree, or you are told (issue 22 item 5): the start-up check of
each drive's CAN settings, on simulated drives set up otherwise (``simulate.params``).

On the fake clock: what is compared and how it is worded, what a silent drive gives, and
that the DP0 rates hold while drives are read. On python-can's virtual bus, end to end:
the log, ``abh3 status``, ``abh3 check --drives``, and ``verify: refuse`` keeping a unit
at its idle word until it is verified again.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Fault, FaultKind, VerifyMode
from abh3_supervisor.core import diagnostics, verifying
from abh3_supervisor.core.commands import RESPONSE_INVALID
from abh3_supervisor.core.supervisor import Notice, SupervisorEvent
from abh3_supervisor.core.verify import VERIFY_DEADLINE, DriveCheck, State, Verification
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.params.telabh3 import pack_float
from abh3_supervisor.protocol import flags, ids
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.headless import run_headless
from tests.support.j1939 import check_j1939, dp0_sends
from tests.support.rig import Rig
from tests.support.served import Served
from tests.support.wire_monitor import WireMonitor

CONFIG = """
buses:
  b: {{interface: virtual, channel: {channel}, simulate: {simulate}}}
units:
  - {{name: left, abh3_id: 1{left}, startup: ["SERVO ON ON", "START ON ON"]}}
  - {{name: right, abh3_id: 3, protocol: "2023"{right}}}
"""
MISMATCHES = "{params: {left: {0x4117: 750}, right: {CAN_HOST_ADDRESS: 5}}}"
ZERO_LINE = "drive 0x4117 CAN_COMMAND_ZERO_TIMEOUT = 750 ms, YAML drive_timeout_ms: 500"
HOST_LINE = "drive 0x4103 CAN_HOST_ADDRESS = 5, YAML host_id: 2"


def text(simulate: str = "true", left: str = "", right: str = "", channel: str = "v") -> str:
    return CONFIG.format(simulate=simulate, left=left, right=right, channel=channel)


def rig(simulate: str = "true", left: str = "", bitrate: int | None = None) -> Rig:
    return Rig(parse_config(text(simulate, left), "v.yaml"), bitrate=bitrate)


class Notices(list[str]):
    """A supervisor subscriber keeping ``unit``'s notices' messages."""

    def __init__(self, unit: str) -> None:
        super().__init__()
        self.unit = unit

    def __call__(self, event: SupervisorEvent) -> None:
        if isinstance(event, Notice) and event.unit == self.unit:
            self.append(event.message)


def check(r: Rig, unit: str) -> list[Verification]:
    """One :class:`DriveCheck` of ``unit`` on the fake clock; its outcome when it ends."""
    out: list[Verification] = []
    channel = r.scheduler.params[unit]
    DriveCheck(r.config, r.config.units[unit], channel, out.append).start()
    return out


# ---------------------------------------------------------------- on the fake clock


def test_a_drive_set_up_as_the_file_says_agrees() -> None:
    r = rig()
    done = check(r, "left")
    r.run(0.5)
    (v,) = done
    assert v.state is State.OK and v.mode is VerifyMode.WARN
    assert [f"0x{row.address:04X}" for row in v.rows] == [
        "0x4100", "0x4101", "0x4102", "0x4103", "0x4105", "0x4107", "0x4117"
    ]  # fmt: skip
    assert all(row.verdict == "ok" for row in v.rows)
    assert v.form is not None and v.form.startswith("CP000095") and "found" in v.form


def test_each_mismatch_is_one_line_with_both_values() -> None:
    r = rig(MISMATCHES, left=", drive_timeout_ms: 500")
    lefts, rights = check(r, "left"), check(r, "right")
    r.run(0.5)
    (left,), (right,) = lefts, rights
    assert left.state is right.state is State.MISMATCH
    assert [m.line() for m in left.mismatches] == [f"{ZERO_LINE} (v.yaml:5)"]  # set: its line
    assert [m.line() for m in right.mismatches] == [f"{HOST_LINE} (the default)"]
    assert right.to_json()["mismatches"][0] == {
        "address": 0x4103,
        "name": "CAN_HOST_ADDRESS",
        "drive": "5",
        "yaml": "host_id: 2 (the default)",
        "verdict": "MISMATCH",
        "text": f"{HOST_LINE} (the default)",
    }


@pytest.mark.parametrize(
    ("params", "line"),
    [
        ("{0x4101: 500000}", None),  # the maker's file: bit/s
        ("{0x4101: 500}", None),  # the table's: kbit/s
        ("{0x4101: 250}", "0x4101 CAN_BITRATE = 250 (kbit/s), YAML buses.b.bitrate: 500000"),
        ("{0x4101: 1000000}", "CAN_BITRATE = 1000000 (bit/s), YAML buses.b.bitrate: 500000"),
        ("{0x4103: -1}", None),  # any host
        ("{0x4105: 20}", None),  # periodic replies
        ("{0x4105: -1}", "-1 (no replies), must be 0 (on receipt) or 1-1000 ms (periodic)"),
        ("{0x4100: 0}", "drive 0x4100 CAN_FUNCTION = 0, must be 2 (control over CAN)"),
        ("{0x4102: 9}", "CAN_ABH3_ADDRESS = 9, YAML abh3_id: 1 (v.yaml:5)"),
        ("{0x4107: 6}", "CAN_BROADCAST_GROUP = 6, YAML brd_group: 5 (the default)"),
        ("{0x4117: 0}", "CAN_COMMAND_ZERO_TIMEOUT = 0 (off), YAML drive_timeout_ms: 500"),
    ],
)
def test_what_counts_as_agreeing(params: str, line: str | None) -> None:
    r = rig(f"{{params: {{left: {params}}}}}")
    done = check(r, "left")
    r.run(0.5)
    (v,) = done
    if line is None:
        assert v.state is State.OK, [m.line() for m in v.mismatches]
    else:
        assert v.state is State.MISMATCH
        assert len(v.mismatches) == 1 and line in v.mismatches[0].line()


def test_a_drive_that_does_not_answer_parameters_is_not_verified_not_an_error() -> None:
    r = rig()
    r.drive("left").faults = (Fault(FaultKind.TP_LOST_CTS, 0.0, 100.0),)
    done = check(r, "left")
    r.run(VERIFY_DEADLINE)
    (v,) = done
    assert v.state is State.NOT_VERIFIED
    assert v.reason == "no CTS from the drive within 1.25 s"
    assert all(row.verdict.startswith("not read") for row in v.rows)
    assert v.holds() is None  # never a reason to hold a unit
    assert not r.scheduler.params["left"].busy  # the rest was never asked


def test_a_drive_reading_no_string_form_is_said_so_within_the_bound() -> None:
    r = rig("{telabh3_form: {left: none}}")
    done = check(r, "left")
    r.run(VERIFY_DEADLINE)
    (v,) = done
    assert v.state is State.NOT_VERIFIED and v.t is not None and v.t < VERIFY_DEADLINE
    assert v.reason is not None and v.reason.startswith("the drive answers none of the TelABH3")


def test_a_refused_address_leaves_that_setting_not_read() -> None:
    r = rig()
    del r.drive("left").tel.params[0x4105]  # a drive without it: NAK
    done = check(r, "left")
    r.run(0.5)
    (v,) = done
    assert v.state is State.NOT_VERIFIED
    assert v.reason == "not read: 0x4105 (the drive refused it (NAK))"


@pytest.mark.wallclock
def test_dp0_rates_hold_within_one_percent_while_drives_are_read() -> None:
    """Two units read over and over for 2 s, a third not at all: every unit's commands keep
    their 50 Hz and no keepalive is late; every transport frame obeys J1939."""
    units = text().replace(
        "units:\n", "units:\n  - {name: other, abh3_id: 5, broadcast: {mask: 0x7f, rate_hz: 10}}\n"
    )
    r = Rig(parse_config(units, "v.yaml"), bitrate=500_000)  # wire time modelled
    r.run(1.0)
    start, end = r.timeline.now, r.timeline.now + 2.0
    rounds = {"left": 0, "right": 0}

    def again(unit: str) -> None:
        def done(v: Verification) -> None:
            assert v.state is State.OK, v
            rounds[unit] += 1
            if r.timeline.now < end:
                again(unit)

        DriveCheck(r.config, r.config.units[unit], r.scheduler.params[unit], done).start()

    again("left")
    again("right")
    r.run(2.1)
    assert min(rounds.values()) > 20  # each unit read its seven settings 20+ times
    for abh3 in (1, 3, 5):
        sent = dp0_sends(r.timeline.frames, abh3, start, end)
        rate = (len(sent) - 1) / (sent[-1] - sent[0])
        assert rate == pytest.approx(50, rel=0.01)
        # a command may wait behind transport frames already queued (0.25 ms each, from
        # both drives being read): never more than a few, never a whole transfer
        assert max(b - a for a, b in itertools.pairwise(sent)) < 0.0225
    assert all(s.stats.timeouts == 0 for s in r.scheduler.slots.values())
    check_j1939(r.timeline.frames)


def test_a_mismatch_is_a_warning_in_the_diagnostics() -> None:
    r = rig(MISMATCHES)
    done = check(r, "left")
    r.run(1.0)
    unit = r.sup.units["left"]
    unit.verify = done[0]
    status = diagnostics.unit_status(unit, r.scheduler, r.timeline.now)
    assert status.level is diagnostics.Level.WARN
    assert status.message == f"drive settings differ from the file: {ZERO_LINE} (the default)"
    values = dict(status.values)
    assert values["drive settings"] == "mismatch"


# ---------------------------------------------------------------- the setting


@pytest.mark.parametrize(
    ("value", "mode"),
    [("warn", VerifyMode.WARN), ("refuse", VerifyMode.REFUSE), ("off", VerifyMode.OFF)],
)
def test_verify_is_a_unit_setting(value: str, mode: VerifyMode) -> None:
    config = parse_config(text(left=f", verify: {value}"))  # a bare off is YAML's false
    assert config.units["left"].verify is mode and config.units["right"].verify is VerifyMode.WARN


@pytest.mark.parametrize("value", ["maybe", "on", "1"])
def test_a_wrong_verify_is_a_file_line_error(value: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(text(left=f", verify: {value}"), "v.yaml")
    assert any(p.startswith("v.yaml:5: units[0].verify: ") for p in info.value.problems)


# ---------------------------------------------------------------- end to end


@pytest.mark.wallclock
def test_mismatches_are_logged_at_start(caplog: pytest.LogCaptureFixture) -> None:
    config = parse_config(text(MISMATCHES, channel="v-log"), "v.yaml")
    with caplog.at_level(logging.INFO):
        code = asyncio.run(run_headless(config, duration=1.0, record=None, status_interval=0))
    assert code == 0
    log = caplog.text
    assert f"unit left: {ZERO_LINE} (the default)" in log
    assert f"unit right: {HOST_LINE} (the default)" in log
    assert "unit left: the drive's CAN settings differ from the file (1 of 7)" in log
    assert "running as the file says (verify: warn)" in log
    assert "unit left: startup 'SERVO ON ON' → ''" in log  # warn: it runs
    assert "unit left: the drive reads TelABH3 strings as CP000095" in log
    assert "pin it with `telabh3: {header: false, checksum: with_header}`" in log


@pytest.mark.wallclock
def test_abh3_status_shows_the_mismatch(tmp_path: Path) -> None:
    served = Served(tmp_path)
    served.config = parse_config(text(MISMATCHES, channel="v-status"), "v.yaml")
    with served:
        client = ControlClient(served.path)
        try:
            deadline = time.monotonic() + 10
            while True:  # the check runs in the background: ≤ 2 s
                state = client.call("state")
                if all(u["verify"]["state"] != "pending" for u in state["units"].values()):
                    break
                assert time.monotonic() < deadline, state["units"]["left"]["verify"]
                time.sleep(0.05)
        finally:
            client.close()
        status = subprocess.run(
            [sys.executable, "-m", "abh3_supervisor", "status", "--connect", str(served.path)],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent.parent,
            timeout=30,
        )
    lines = {line.split(":")[0]: line for line in status.stdout.splitlines()}
    assert lines["left"].endswith(f" · drive settings MISMATCH: {ZERO_LINE} (the default)")
    assert lines["right"].endswith(f" · drive settings MISMATCH: {HOST_LINE} (the default)")
    verify = state["units"]["right"]["verify"]
    assert verify["state"] == "mismatch" and verify["mode"] == "warn" and verify["held"] is None
    assert [m["address"] for m in verify["mismatches"]] == [0x4103]
    assert len(verify["rows"]) == 7 and verify["form"].startswith("CP000095")


@pytest.mark.wallclock
def test_check_drives_prints_the_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(text(MISMATCHES, channel="v-check"))
    assert main(["check", str(bad), "--drives"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["unit", "address", "name", "drive", "YAML", "verdict"]
    rows = {(line.split()[0], line.split()[1]): line for line in out[1:15]}
    assert rows[("left", "0x4117")].split()[2:] == [
        "CAN_COMMAND_ZERO_TIMEOUT", "750", "ms", "drive_timeout_ms:", "500", "(the", "default)",
        "MISMATCH",
    ]  # fmt: skip
    assert rows[("right", "0x4103")].endswith("MISMATCH") and " 5 " in rows[("right", "0x4103")]
    assert rows[("left", "0x4103")].endswith("ok")
    assert "left (bus b, drive 1): 1 setting(s) differ from the file" in out
    assert any(line.startswith("left (bus b, drive 1): TelABH3 form CP000095") for line in out)
    good = tmp_path / "good.yaml"
    good.write_text(text(channel="v-check-ok"))
    assert main(["check", str(good), "--drives", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert {name: v["state"] for name, v in doc.items()} == {"left": "ok", "right": "ok"}


@pytest.mark.wallclock
def test_check_drives_asks_for_abh3_simulate_when_its_drives_run_elsewhere_and_none_answers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "ext.yaml"
    cfg.write_text(
        "buses:\n  b: {interface: virtual, channel: v-ext, simulate: {external: true}}\n"
        "units:\n  - {name: left, abh3_id: 1}\n"
    )
    assert main(["check", str(cfg), "--drives"]) == 1
    assert capsys.readouterr().err.splitlines()[-1] == (
        "left: no drive answered, and the file's drives there are simulated in another "
        f"process: is `abh3 simulate {cfg}` running?"
    )


@pytest.mark.wallclock
def test_check_drives_names_a_drive_that_reads_no_form(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "none.yaml"
    path.write_text(text("{telabh3_form: {right: none}}", channel="v-none"))
    assert main(["check", str(path), "--drives"]) == 1
    out = capsys.readouterr().out
    assert (
        "right (bus b, drive 3): not verified: the drive answers none of the TelABH3 forms" in out
    )
    assert "left (bus b, drive 1): agrees with the file" in out


@pytest.mark.wallclock
def test_check_drives_usage_errors_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "typo.yaml"
    path.write_text(text(left=", verify: maybe"))
    assert main(["check", str(path), "--drives"]) == 2
    assert "typo.yaml:5: units[0].verify:" in capsys.readouterr().err


@pytest.mark.wallclock
def test_refuse_keeps_the_unit_idle_until_it_is_verified_again(wire: WireMonitor) -> None:
    config = parse_config(text(MISMATCHES, left=", verify: refuse", channel="v-refuse"), "v.yaml")
    notices = Notices("left")

    async def scenario() -> None:
        async with Runtime(config) as rt:
            sup = rt.supervisor
            sup.subscribe(notices)
            drive = rt.sims["b"].drives[1]
            seen: list[int] = []
            received = drive.on_frame

            def watch(arbitration_id: int, data: bytes, now: float) -> None:
                if arbitration_id == ids.dp0_command_id(1, 2):
                    seen.append(int.from_bytes(data[4:8], "little"))
                received(arbitration_id, data, now)

            drive.on_frame = watch  # type: ignore[method-assign]
            servo = sup.units["left"].layout.servo.both | sup.units["left"].layout.start.both
            assert sup.units["left"].verify.state is State.PENDING
            assert sup.apply_text("left", "SERVO ON ON") == RESPONSE_INVALID  # not yet
            assert rt.verifying is not None
            await asyncio.wait_for(asyncio.shield(rt.verifying), 5)
            verify = sup.units["left"].verify
            assert verify.state is State.MISMATCH and verify.holds() is not None
            with wire.held(1, "verify: refuse, a mismatch"):  # judged on the wire too
                assert sup.apply_text("left", "SERVO ON ON") == RESPONSE_INVALID
                assert sup.apply_text("left", "START ON ON") == RESPONSE_INVALID
                assert sup.apply_text("right", "SERVO ON ON") == ""  # warn: the other runs
                sup.apply_text("left", "VEL 100 50")  # whatever it answers: no setpoint out
                for _ in range(5):  # the held unit keeps being sent its idle word
                    assert await sup.wait_exchange("left", sup.clock(), 1.0)
            assert seen and not any(word & servo for word in seen)
            assert not drive.alarm_word() & flags.CAN_COMM_ERROR  # its keepalive flows
            # the drive is set as the file says, and the unit is told to verify again
            drive.tel.params[0x4117] = pack_float(500)
            again = (await verifying.verify_units(sup, ["left"]))["left"]
            assert again.state is State.OK and again.holds() is None
            await sup.command("left", "VEL 0 0")  # a frame after the start-up commands
            assert drive.inputs & sup.units["left"].layout.servo.both  # start-up ran now

    asyncio.run(scenario())
    refused = [n for n in notices if "refused" in n]
    assert (
        "'SERVO ON ON' refused: unit 'left' is held at its idle word: its drive's CAN "
        "settings are being compared with the file (verify: refuse)"
    ) in refused
    assert (
        "'SERVO ON ON' refused: unit 'left' is held at its idle word: its drive's CAN "
        f"settings differ from the file (verify: refuse): {ZERO_LINE} (the default); fix the "
        "drive or the file, then verify it again"
    ) in refused
    assert any("held at its idle word (SERVO, START, brake, torque refused)" in n for n in notices)
    assert "the drive's CAN settings agree with the file (7 read; TelABH3 CP000095" in notices[-1]


@pytest.mark.wallclock
def test_refuse_fails_closed_on_a_drive_that_cannot_be_read() -> None:
    """Not verified under verify: refuse is held: its start-up commands never run, the
    drive sees only the safe word, a VEL is refused in its answer, and the hold says why."""
    config = parse_config(
        text("{telabh3_form: {left: none}}", left=", verify: refuse", channel="v-unread"), "v.yaml"
    )

    async def scenario() -> tuple[Verification, str, int, float]:
        async with Runtime(config) as rt:
            assert rt.verifying is not None
            await asyncio.wait_for(asyncio.shield(rt.verifying), 5)
            answer = await rt.supervisor.command("left", "VEL 100 0")
            await rt.supervisor.wait_exchange("left", rt.supervisor.clock(), 1.0)
            drive = rt.sims["b"].drives[1]
            return rt.supervisor.units["left"].verify, answer, drive.inputs, drive.cmd_raw[0]

    v, answer, inputs, cmd = asyncio.run(scenario())
    assert v.state is State.NOT_VERIFIED
    assert v.holds() is not None and "could not be verified" in v.holds()  # type: ignore[operator]
    assert answer == RESPONSE_INVALID
    layout = flags.LAYOUT_2021
    assert not inputs & (layout.servo.both | layout.start.both | layout.brake_release)
    assert cmd == 0


@pytest.mark.wallclock
def test_the_shipped_faults_config_rehearses_both_mismatches(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from abh3_supervisor.config import load_config

    config = load_config(Path(__file__).parent.parent / "configs" / "faults.yaml")
    with caplog.at_level(logging.INFO):
        code = asyncio.run(run_headless(config, duration=1.0, record=None, status_interval=0))
    assert code == 0
    assert f"unit left: {ZERO_LINE} (the default)" in caplog.text
    assert f"unit right: {HOST_LINE} (the default)" in caplog.text
    assert "not verified" not in caplog.text  # its transport faults start after the check


@pytest.mark.wallclock
@pytest.mark.parametrize(
    ("form", "shown"),
    [
        ("{header: false, checksum: with_header}", "CP000095 (no header, checksum counting FFFF)"),
        ("{header: true}", "FFFFCP000095 (the serial form: FFFF header)"),
        ("{header: false, checksum: as_sent}", "CP0000AD (no header, checksum over what is sent)"),
    ],
)
def test_check_drives_names_the_form_each_drive_reads(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], form: str, shown: str
) -> None:
    path = tmp_path / "form.yaml"
    path.write_text(text(f"{{telabh3_form: {{left: {form}}}}}", channel=f"v-form-{len(form)}"))
    assert main(["check", str(path), "--drives"]) == 0  # found without a telabh3: setting
    out = capsys.readouterr().out
    assert "left (bus b, drive 1): agrees with the file" in out
    assert f"left (bus b, drive 1): TelABH3 form {shown}, found; pin it with `telabh3: " in out


def test_a_held_unit_switches_nothing_on_but_data_select_and_error_reset(rig: Rig) -> None:
    """verify: refuse holds the idle word: a brake released with the servo off would let
    a load fall, so BRAKE and TORQUE are refused like SERVO and START."""
    from abh3_supervisor.core.verify import Row

    row = Row(0x4117, "750 ms", "drive_timeout_ms: 500", False)
    rig.sup.units["left"].verify = Verification(State.MISMATCH, VerifyMode.REFUSE, rows=(row,))
    before = rig.sup.units["left"].inputs
    for text in ("SERVO ON ON", "START ON ON", "BRAKE ON ON", "TORQUE ON ON", "DIR ON ON"):
        assert rig.sup.apply_text("left", text) == RESPONSE_INVALID, text
    assert rig.sup.units["left"].inputs == before
    for text in ("SELECT 3 3", "RESET ON ON", "RESET OFF OFF", "SERVO OFF OFF"):
        assert rig.sup.apply_text("left", text) == "", text


@pytest.mark.wallclock
def test_abh3_verify_asks_a_running_supervisor_and_releases_a_held_unit(tmp_path: Path) -> None:
    """`abh3 verify UNIT`: the running supervisor reads the drive again; fixed, the unit a
    `verify: refuse` held runs its start-up commands."""
    text = (Path(__file__).parent.parent / "configs" / "demo.yaml").read_text()
    text = text.replace(
        "    simulate: ", "    simulate:\n      params: {left: {0x4117: 750}}\n    "
    )
    assert "0x4117: 750" in text  # the demo still has its simulate section
    text = text.replace('protocol: "2021"', 'verify: refuse\n    protocol: "2021"')
    config = tmp_path / "held.yaml"
    config.write_text(text)
    sock = tmp_path / "s" / "held.sock"
    run = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", str(config), "--headless", "--socket",
         str(sock), "--status-interval", "0"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert run.stderr is not None
    try:
        for line in run.stderr:
            if "held at its idle word" in line:
                break
        else:
            pytest.fail("the run ended without holding the unit")

        def abh3(*args: str) -> subprocess.CompletedProcess[str]:
            cmd = [sys.executable, "-m", "abh3_supervisor", *args, "--connect", str(sock)]
            return subprocess.run(cmd, capture_output=True, text=True, timeout=60)

        held = abh3("verify", "left")
        assert held.returncode == 1 and "HELD: " in held.stdout and "MISMATCH" in held.stdout
        fix = ["param", "--connect", str(sock), "set", "left", "0x4117", "500", "--yes"]
        assert (
            subprocess.run([sys.executable, "-m", "abh3_supervisor", *fix], timeout=60).returncode
            == 0
        )
        agreed = abh3("verify", "left")
        assert agreed.returncode == 0 and "left (bus demo, drive 1): agrees" in agreed.stdout
        assert abh3("verify", "nobody").returncode == 2
        state = json.loads(abh3("status", "--json").stdout)["units"]["left"]
        assert state["verify"]["state"] == "ok" and state["verify"]["held"] is None
    finally:
        run.terminate()
        run.communicate(timeout=30)


@pytest.mark.wallclock
def test_a_drive_without_its_command_zero_timeout_is_held_even_under_warn(
    wire: WireMonitor,
) -> None:
    """0x4117 = 0: nothing would stop its motors were this host to die. Under the default
    ``verify: warn`` its start-up commands wait for the check, which holds it."""
    config = parse_config(text("{params: {left: {0x4117: 0}}}", channel="v-unsafe"), "v.yaml")
    notices = Notices("left")

    async def scenario() -> None:
        async with Runtime(config) as rt:
            sup = rt.supervisor
            sup.subscribe(notices)
            drive = rt.sims["b"].drives[1]
            assert sup.units["left"].cfg.verify is VerifyMode.WARN
            assert rt.verifying is not None
            await asyncio.wait_for(asyncio.shield(rt.verifying), 5)
            verify = sup.units["left"].verify
            assert verify.state is State.MISMATCH
            held = verify.holds()
            assert held is not None and "command-zero timeout is off" in held
            with wire.held(1, "0x4117 off"):
                assert sup.apply_text("left", "SERVO ON ON") == RESPONSE_INVALID
                for _ in range(5):
                    assert await sup.wait_exchange("left", sup.clock(), 1.0)
            assert not drive.inputs & sup.units["left"].layout.servo.both  # start-up never ran
            assert sup.units["right"].verify.holds() is None  # the other drive runs
            drive.tel.params[0x4117] = pack_float(500)  # set as it must be, verified again
            again = (await verifying.verify_units(sup, ["left"]))["left"]
            assert again.state is State.OK and again.holds() is None
            await sup.command("left", "VEL 0 0")
            assert drive.inputs & sup.units["left"].layout.servo.both  # start-up ran now

    asyncio.run(scenario())
    assert any("held at its idle word (SERVO, START, brake, torque refused)" in n for n in notices)


@pytest.mark.wallclock
def test_writing_0x4117_off_on_a_running_supervisor_holds_the_unit(wire: WireMonitor) -> None:
    """A parameter write to a setting the start-up check compares is checked again at once,
    under the write's lock: 0x4117 = 0 leaves the unit held before it can move."""
    from abh3_supervisor.service.param_ops import ParamOps

    config = parse_config(text(channel="v-write-off"), "v.yaml")

    async def scenario() -> None:
        async with Runtime(config) as rt:
            sup = rt.supervisor
            assert rt.verifying is not None
            await asyncio.wait_for(asyncio.shield(rt.verifying), 5)
            assert sup.units["left"].verify.holds() is None
            await sup.command("left", "SERVO OFF OFF")  # its start-up switched it on
            ops = ParamOps(sup, lambda unit: rt.pumps["b"].wake())
            await ops.write("left", 0x4117, pack_float(0), force=True, source="test")
            held = sup.units["left"].verify.holds()
            assert held is not None and "command-zero timeout is off" in held
            with wire.held(1, "0x4117 written off"):
                assert sup.apply_text("left", "SERVO ON ON") == RESPONSE_INVALID
                for _ in range(3):
                    assert await sup.wait_exchange("left", sup.clock(), 1.0)

    asyncio.run(scenario())
