"""A simulated drive's power and cable (``abh3 simulate``'s commands), and what the
supervisor does about them: a drive that comes back never moves until commanded anew."""

from __future__ import annotations

import json

import pytest

from abh3_supervisor.params import table
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.simulator import SimDrive
from abh3_supervisor.simulator.control import obey
from abh3_supervisor.simulator.drive import BOOT_S
from abh3_supervisor.simulator.telabh3 import COMMAND_ZERO
from abh3_supervisor.simulator.watch import Watch
from tests.support.rig import Rig

L21 = flags.LAYOUT_2021
MOVE = L21.servo.both | L21.start.both | L21.select(1, 1)


def command(drive: SimDrive, t: float, ay: int = 0, host: int = 2) -> list[tuple[int, bytes]]:
    drive.on_frame(
        ids.dp0_command_id(drive.abh3_id, host), frames.encode_dp0_command(ay, 0, MOVE), t
    )
    return drive.poll(t + 0.001)


def stream(drive: SimDrive, start: float, end: float, ay: int = 1500) -> float:  # 300 min⁻¹
    t = start
    while t < end:
        command(drive, t, ay)
        t += 0.02
    return t - 0.02  # the last command's time


def moving(rig: Rig, unit: str) -> bool:
    return bool(max(abs(v) for v in rig.drive(unit).vel) > 1.0)


def start_both(rig: Rig) -> None:
    for unit, vel in (("left", "VEL 300 0"), ("right", "VEL 200 200")):
        for text in ("SERVO ON ON", "START ON ON", vel):
            assert rig.sup.apply_text(unit, text) == ""


def asked(drive: SimDrive, t: float) -> list[tuple[int, bytes]]:
    """A request for its DP0 reply: a read, which commands nothing."""
    drive.on_frame(ids.request_id(drive.abh3_id, 2), frames.encode_request(frames.PGN_DP0), t)
    return drive.poll(t + 0.001)


def test_a_drive_without_power_hears_and_says_nothing_and_runs_down() -> None:
    drive = SimDrive(1, now=0.0)
    stream(drive, 0.0, 1.0)
    before = drive.vel[0]
    assert before > 250
    drive.power_off(1.0)
    assert command(drive, 1.01) == [] and asked(drive, 1.02) == []  # no reply
    drive.advance(1.05)
    assert 0 < drive.vel[0] < before  # running down at its ramp, not stopped dead
    drive.advance(2.0)
    assert max(abs(v) for v in drive.vel) < 0.5


def test_power_back_boots_then_answers_servo_off_and_moves_only_when_commanded_again() -> None:
    drive = SimDrive(1, now=0.0)
    stream(drive, 0.0, 1.0)
    drive.power_off(1.0)
    drive.power_on(2.0)
    assert asked(drive, 2.0 + BOOT_S - 0.01) == []  # still booting
    assert len(asked(drive, 2.0 + BOOT_S)) == 1  # answers
    assert drive.control_word() & (L21.servo.both | L21.start.both) == 0  # servo off
    assert drive.pulses == [0.0, 0.0] and drive.errors == 0
    assert drive.alarm_word() & flags.CAN_COMM_ERROR  # no command heard since it booted
    drive.advance(3.0)
    assert drive.vel == [0.0, 0.0]  # nothing moves by itself
    stream(drive, 3.1, 3.6)  # the host commands it again: it moves
    assert drive.vel[0] > 100


def test_a_power_cycle_reloads_the_table_as_set_up_unless_kept() -> None:
    for keep, expected in ((False, 500), (True, 900)):
        drive = SimDrive(1, now=0.0)
        drive.tel.params[COMMAND_ZERO] = table.to_word(900, table.kind_of(COMMAND_ZERO))
        drive.power_off(1.0)
        drive.power_on(1.5, keep_writes=keep)
        assert drive.command_zero_ms == expected


def test_unplugged_it_runs_on_until_its_own_timeout_stops_it() -> None:
    drive = SimDrive(1, now=0.0)
    watch = Watch({"left": drive})
    last = stream(drive, 0.0, 1.0)
    list(watch.sample(1.0))
    drive.plugged = False
    stream(drive, 1.0, 2.0)  # the host goes on sending: the drive hears none of it
    events = [e for t in range(100, 300) for e in watch.sample(t / 100)]
    kinds = [e["event"] for e in events if e["event"] != "state"]
    assert kinds == ["command_zero_timeout", "standing"]
    timeout = next(e for e in events if e["event"] == "command_zero_timeout")
    assert timeout["last_command"] == pytest.approx(last)  # what it heard before the pull
    assert timeout["at"] == pytest.approx(last + 0.5)


def test_the_watch_places_the_stop_after_the_last_command() -> None:
    drive = SimDrive(1, now=0.0)
    watch = Watch({"left": drive})
    last = stream(drive, 0.0, 1.0)
    events = [e for t in range(0, 250) for e in watch.sample(t / 100)]
    kinds = [e["event"] for e in events if e["event"] != "state"]
    assert kinds == ["moving", "command_zero_timeout", "standing"]
    standing = next(e for e in events if e["event"] == "standing")
    # the timeout, then the ramp down from 300 min⁻¹ at 3000 min⁻¹/s, sampled every 10 ms
    assert 500 + 100 <= standing["since_last_command_ms"] <= 500 + 100 + 10 + 1e-6
    assert sum(e["event"] == "state" for e in events) > 50  # a sample while it turns
    del last


def test_control_lines() -> None:
    drives = {"left": SimDrive(1, now=0.0), "right": SimDrive(2, now=0.0)}
    assert obey("power off left", drives, 1.0).text == "ok power off left"
    assert not drives["left"].powered and drives["right"].powered
    answer = obey("power on all keep", drives, 2.0)
    assert answer.text == "ok power on left right"
    assert [e["event"] for e in answer.events] == ["power_on", "power_on"]
    assert obey("unplug right", drives, 2.0).text == "ok unplugged right"
    assert not drives["right"].plugged
    assert obey("plug right", drives, 2.0).text == "ok plugged right"
    status = obey("status", drives, 2.0).text.splitlines()
    assert status[0] == "ok status"
    assert json.loads(status[2])["unit"] == "right"
    assert obey("power off nobody", drives, 3.0).text == (
        "error: no simulated unit 'nobody' (units: left, right)"
    )
    assert obey("power on left twice", drives, 3.0).text.startswith("error: power on UNIT")
    assert obey("dance", drives, 3.0).text == "error: unknown command 'dance'; try help"
    assert "unplug UNIT" in obey("help", drives, 3.0).text
    assert obey("quit", drives, 3.0).quit


def test_the_supervisor_keeps_a_drive_that_lost_its_power_stopped_when_it_returns(
    rig: Rig,
) -> None:
    start_both(rig)
    rig.run(1.0)
    assert moving(rig, "left")
    drive = rig.drive("left")
    drive.power_off(rig.timeline.now)
    rig.run(1.5)  # offline: the supervisor holds it
    assert not moving(rig, "left") and rig.sup.units["left"].online is False
    drive.power_on(rig.timeline.now)
    rig.run(BOOT_S + 1.0)
    assert rig.sup.units["left"].online is True  # back, answering …
    assert not moving(rig, "left")  # … and standing: its old setpoint was dropped …
    servo = L21.servo.both | L21.start.both
    assert not drive.control_word() & servo  # … and it was not switched on again
    assert moving(rig, "right")  # the other drive was never touched
    # a velocity alone is refused, in its answer: the robot is not switched on
    assert rig.sup.apply_text("left", "VEL 200 0") == "Invalid Command."
    rig.run(0.5)
    assert not moving(rig, "left")
    for text in ("SERVO ON ON", "START ON ON", "VEL 200 0"):  # switched on anew: it moves
        assert rig.sup.apply_text("left", text) == ""
    rig.run(0.5)
    assert moving(rig, "left")


def test_the_supervisor_keeps_a_drive_whose_cable_came_back_stopped(rig: Rig) -> None:
    start_both(rig)
    rig.run(1.0)
    drive = rig.drive("left")
    drive.plugged = False
    rig.run(1.5)
    assert not moving(rig, "left")  # its own command-zero timeout
    drive.plugged = True
    rig.run(1.0)
    assert rig.sup.units["left"].online is True
    assert not moving(rig, "left")


def test_a_data_page_1_frame_is_no_command_to_the_drive() -> None:
    drive = SimDrive(1, now=0.0)
    dp1 = ids.dp0_command_id(1, 2) | 1 << 24
    drive.on_frame(dp1, frames.encode_dp0_command(1500, 0, MOVE), 0.0)
    assert drive.poll(0.01) == [] and drive.last_command is None


def test_a_drive_powered_on_is_not_commanded_until_a_host_speaks() -> None:
    drive = SimDrive(1, now=0.0)
    watch = Watch({"left": drive})
    stream(drive, 0.0, 1.0)
    list(watch.sample(1.0))
    drive.power_off(1.0)
    list(watch.sample(1.6))  # its own timeout, standing
    drive.power_on(2.0)
    events = [e for t in range(200, 400) for e in watch.sample(t / 100)]
    assert "commanded" not in [e["event"] for e in events]  # nobody spoke to it


def test_control_answers_say_the_form_and_cut_a_long_line() -> None:
    drives = {"left": SimDrive(1, now=0.0)}
    assert obey("power off left keep", drives, 0.0).text == (
        "error: power off UNIT|all, not 'power off left keep'"
    )
    garbage = obey("x" * 200_000, drives, 0.0).text
    assert len(garbage) < 120 and garbage.endswith("…'; try help")
    assert obey("", drives, 0.0).text == ""  # no command, no answer
    status = json.loads(obey("status", drives, 0.0).text.splitlines()[1])
    assert status["host"] is None  # never commanded
