"""Readouts speak one vocabulary (issue 21, items 6 and 7).

Velocities are labelled by the unit's model (Y/X for ``travel``, A/B for ``motor``), servo
and start are shown as the drive reports them, ``abh3 decode`` without ``--config`` says
which generation it guessed per address, and a monitor unit's CAN_COMM_ERROR (its drive is
never commanded) reads "no commands (monitor)" everywhere instead of an error. All on the
fake clock with the simulated drives.
"""

from __future__ import annotations

import json
import logging
from typing import Any

import pytest

from abh3_plugins.ros2 import types
from abh3_plugins.ros2.diagnostics import DiagnosticsPublisher
from abh3_supervisor.clients.control import status_lines
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.model import (
    detail_fields,
    fault_lines,
    fault_names,
    overview_row,
    verify_fields,
)
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Role
from abh3_supervisor.core import readouts
from abh3_supervisor.core.diagnostics import Health, Level
from abh3_supervisor.core.eventlog import EventLog, describe
from abh3_supervisor.core.supervisor import FlagChange, SupervisorEvent
from abh3_supervisor.protocol import flags
from abh3_supervisor.service.snapshot import supervisor_state
from tests.support.rig import TWO_UNITS, Rig, present, set_current, set_velocity

# a commanding 2021 travel unit beside a 2023 motor unit that only watches
WATCHED = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: left, abh3_id: 1, broadcast: {mask: 0x7f, rate_hz: 14}}
  - {name: watch, abh3_id: 3, protocol: "2023", velocity_model: motor, role: monitor,
     broadcast: {mask: 0x0f, rate_hz: 8}}
"""
COMM = flags.CAN_COMM_ERROR
NOTE = "no commands (monitor)"


def lines(rig: Rig) -> dict[str, str]:
    """``abh3 status`` lines by unit, from the state the service would serve."""
    out = status_lines(supervisor_state(rig.sup, {}))
    return {line.split(":")[0]: line for line in out}


def driven() -> Rig:
    """TWO_UNITS: left is 2021 travel (Y/X), right 2023 motor (A/B); both moving."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    for unit in ("left", "right"):
        assert rig.sup.apply_text(unit, "SERVO ON ON") == ""
        assert rig.sup.apply_text(unit, "START ON ON") == ""
    set_velocity(rig.sup, "left", 50, 0, source=present(rig.sup, "left"))  # Y/X: travel 50, no turn
    set_velocity(rig.sup, "right", 100, 0, source=present(rig.sup, "right"))  # A/B: only motor A
    rig.run(3.0)
    return rig


# ---------------------------------------------------------------- one axis vocabulary


def test_status_lines_label_each_units_velocities_by_its_own_model() -> None:
    rig = driven()
    got = lines(rig)
    assert got["left"] == (
        "left: online 50.0/50 Hz · cmd Y/X 50.0 0.0 · fbk Y/X 50.0 0.0 (A/B 50.0 50.0)"
        " · servo Y/X ON/ON · start Y/X ON/ON · no errors"
    )
    assert got["right"] == (
        "right: online 50.0/50 Hz · cmd A/B 100.0 0.0 · fbk A/B 100.0 0.0 (Y/X 50.0 50.0)"
        " · servo A/B ON/ON · start A/B ON/ON · no errors"
    )


def test_servo_and_start_are_what_the_drive_reports_not_what_was_commanded() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    before = lines(rig)
    assert "servo Y/X ?/? · start Y/X ?/? (not reported yet)" in before["left"]
    assert "servo A/B ?/? · start A/B ?/? (not reported yet)" in before["right"]
    rig.sup.apply_text("right", "SERVO ON OFF")
    rig.sup.apply_text("left", "SERVO ON ON")
    rig.drive("right").inject_error(flags.FAULT.mask("A_OVERCURRENT"))  # servo stays off
    rig.run(2.0)
    got = lines(rig)
    assert "servo A/B off/off · start A/B off/off" in got["right"]  # commanded ON/off
    assert got["right"].endswith("errors A_OVERCURRENT")
    assert "servo Y/X ON/ON · start Y/X off/off" in got["left"]  # broadcast 1 in 2021
    assert "ago" not in got["left"]


def test_a_report_older_than_a_second_says_its_age() -> None:
    rig = driven()
    rig.drive("left").silent = True
    rig.run(2.5)
    left = lines(rig)["left"]
    assert left.startswith("left: OFFLINE")
    age = rig.timeline.now - rig.sup.units["left"].status[1][0]  # broadcast 1 every 0.5 s
    assert 2.5 < age <= 3.0 and left.endswith(
        f"start Y/X ON/ON (reported {age:.1f} s ago) · no errors"
    )


def test_the_state_carries_the_model_and_the_reported_switches_with_their_time() -> None:
    rig = driven()
    state = supervisor_state(rig.sup, {})
    left, right = state["units"]["left"], state["units"]["right"]
    assert (left["velocity_model"], right["velocity_model"]) == ("travel", "motor")
    for unit in (left, right):
        assert unit["reported"]["servo"] == [True, True]
        assert unit["reported"]["start"] == [True, True]
        assert 0 <= state["t"] - unit["reported"]["t"] <= 0.5  # left: broadcast 1 twice a second
    assert right["reported"]["t"] == right["feedback"]["t"]  # 2023: the DP0 reply's word
    assert left["reported"]["t"] == pytest.approx(rig.sup.units["left"].status[1][0])
    assert left["words"]["error"]["notes"] == {}
    # what was there before is unchanged, and a client built for it still reads the state
    assert set(left) >= {"bus", "abh3_id", "protocol", "role", "online", "setpoint"}
    assert set(left["feedback"]) == {"t", "vel_a", "vel_b", "vel_y", "vel_x", "control"}
    mirror = Mirror.of(rig.config)
    mirror.apply(json.loads(json.dumps(state)))
    assert mirror.units["right"].feedback is not None
    assert mirror.units["right"].feedback.vel_a == 100.0


def test_status_lines_of_an_older_service_label_both_pairs() -> None:
    rig = driven()
    state = supervisor_state(rig.sup, {})
    for unit in state["units"].values():
        del unit["velocity_model"], unit["reported"]
    got = {line.split(":")[0]: line for line in status_lines(state)}
    assert "cmd AY/BX 50.0 0.0 · fbk A/B 50.0 50.0 Y/X 50.0 0.0" in got["left"]
    assert "servo" not in got["left"]  # it did not say


def test_a_current_command_is_labelled_and_in_percent() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.sup.apply_text("right", "TORQUE ON ON")
    set_current(rig.sup, "right", 12.5, -3, source=present(rig.sup, "right"))
    assert "cmd current A/B 12.50 -3.00 %" in lines(rig)["right"]


# ---------------------------------------------------------------- monitors read calmly


def watched() -> Rig:
    rig = Rig(parse_config(WATCHED, "watched.yaml"))
    rig.run(3.0)
    watch = rig.sup.units["watch"]
    assert watch.words["error"] & COMM and watch.words["alarm"] & COMM  # the drive's view
    return rig


def test_the_rule_is_one_function_of_the_role() -> None:
    assert readouts.normal_faults(Role.MONITOR) == COMM
    assert readouts.normal_faults(Role.COMMAND) == 0
    reading = readouts.read_faults(Role.MONITOR, COMM | flags.FAULT.mask("A_PDU"))
    assert reading.names == ["A_PDU"] and reading.notes == [NOTE]
    assert reading.labelled() == ["A_PDU", f"CAN_COMM_ERROR ({NOTE})"]
    assert readouts.read_faults(Role.COMMAND, COMM).names == ["CAN_COMM_ERROR"]


def test_status_shows_a_monitors_comm_error_as_no_commands() -> None:
    rig = watched()
    got = lines(rig)
    assert got["watch"] == (
        "watch: online 50.0/50 Hz · cmd none (monitor) · fbk A/B 0.0 0.0 (Y/X 0.0 0.0)"
        f" · servo A/B off/off · start A/B off/off · no errors · {NOTE}"
    )
    assert "CAN_COMM_ERROR" not in got["watch"]
    state = supervisor_state(rig.sup, {})["units"]["watch"]
    assert state["words"]["error"]["names"] == ["CAN_COMM_ERROR"]  # the word as it is
    assert state["words"]["error"]["notes"] == {"CAN_COMM_ERROR": NOTE}
    rig.drive("watch").inject_error(flags.FAULT.mask("B_OVERCURRENT"))
    rig.run(1.0)
    assert lines(rig)["watch"].endswith(f"errors B_OVERCURRENT · {NOTE}")


def test_a_commanding_units_comm_error_is_still_an_error_in_status() -> None:
    rig = watched()
    rig.drive("left").inject_error(COMM)
    rig.run(1.0)
    assert lines(rig)["left"].endswith("errors CAN_COMM_ERROR")


def test_the_tui_shows_a_monitors_comm_error_as_a_note() -> None:
    rig = watched()
    rig.drive("left").inject_error(COMM)
    rig.run(1.0)
    mirror = Mirror.of(rig.config)
    mirror.apply(supervisor_state(rig.sup, {}))
    assert fault_names(mirror, "watch") == [("note", NOTE)]
    assert fault_names(mirror, "left") == [("error", "CAN_COMM_ERROR")]
    words = mirror.units["watch"].words
    monitor = dict(fault_lines(words["error"], words["alarm"], Role.MONITOR))
    assert "error" not in monitor and "alarm" not in monitor
    assert monitor["note"] == f"·· 22 CAN_COMM_ERROR: {NOTE}"
    commanding = dict(fault_lines(words["error"], words["alarm"]))
    assert commanding["error"] == "✖▲ 22 CAN_COMM_ERROR"
    # the overview counts faults, not notes: the monitor has none, left has its error
    assert overview_row(mirror, "watch")["faults"] == "–"
    assert overview_row(mirror, "left")["faults"].startswith("✖1")


def test_the_unit_tab_shows_the_drive_settings_check() -> None:
    """core/verify.py's state, as the service sends it, on the unit tab."""
    mismatch = {
        "state": "mismatch",
        "mismatches": [{"text": "drive 0x4117 CAN_COMMAND_ZERO_TIMEOUT = 750 ms, "
                                "YAML drive_timeout_ms: 500 (the default)"}],
        "held": "its drive's CAN settings differ from the file (verify: refuse): …",
    }  # fmt: skip
    assert verify_fields(mismatch) == [
        "drive settings MISMATCH: drive 0x4117 CAN_COMMAND_ZERO_TIMEOUT = 750 ms, "
        "YAML drive_timeout_ms: 500 (the default)",
        "HELD: its drive's CAN settings differ from the file (verify: refuse): …",
    ]
    assert verify_fields({"state": "not verified", "reason": "no answer"}) == [
        "drive settings not verified (no answer)"
    ]
    assert verify_fields({"state": "ok"}) == ["drive settings ok"]
    assert verify_fields(None) == []  # an older service
    rig = watched()
    mirror = Mirror.of(rig.config)
    mirror.apply(supervisor_state(rig.sup, {}))
    assert mirror.units["left"].verify is not None
    shown = detail_fields(mirror, "left")
    assert any(f.startswith("drive settings ") for f in shown)


def test_diagnostics_say_ok_for_a_monitors_comm_error_alone() -> None:
    rig = watched()
    sent: list[Any] = []
    clock = rig.timeline.clock
    publisher = DiagnosticsPublisher(
        Health(rig.sup), sent.append, types, 1.0, wall_ns=lambda: int(clock() * 1e9)
    )
    publisher.tick(clock())
    watch = next(s for s in sent[-1].status if s.name.endswith("unit watch"))
    assert watch.level == Level.OK  # the byte /diagnostics carries
    assert watch.message == f"online, {NOTE}"
    assert {kv.key: kv.value for kv in watch.values}["error bits"] == f"CAN_COMM_ERROR ({NOTE})"
    rig.drive("watch").inject_error(flags.FAULT.mask("BRAKE_FAULT"))
    rig.run(1.0)
    publisher.changed(clock())
    watch = next(s for s in sent[-1].status if s.name.endswith("unit watch"))
    assert watch.level == Level.ERROR
    assert watch.message == f"error: BRAKE_FAULT; {NOTE}"


def test_diagnostics_still_error_for_a_commanding_units_comm_error() -> None:
    rig = watched()
    rig.drive("left").inject_error(COMM)
    rig.run(1.0)
    statuses = Health(rig.sup).statuses(rig.timeline.now)
    left = next(s for s in statuses if s.name.endswith("unit left"))
    assert left.level == Level.ERROR and left.message == "error: CAN_COMM_ERROR"


def events(rig: Rig) -> list[SupervisorEvent]:
    return [e for e in rig.events if isinstance(e, SupervisorEvent)]


def test_the_event_log_notes_a_monitors_comm_error_at_info() -> None:
    rig = watched()
    log = EventLog(rig.sup)
    described = [line for e in events(rig) if (line := log.line(e)) is not None]
    assert (logging.INFO, f"unit watch: error +CAN_COMM_ERROR ({NOTE})") in described
    assert (logging.INFO, f"unit watch: alarm +CAN_COMM_ERROR ({NOTE})") in described
    assert all(level < logging.WARNING for level, _ in described), described
    # another error beside it is an error; a commanding unit's bit 22 is one too
    both = FlagChange("watch", 4.0, "error", COMM, COMM | flags.FAULT.mask("A_PDU"))
    assert describe(both, rig.sup) == (logging.ERROR, "unit watch: error +A_PDU (A PDU)")
    left = FlagChange("left", 4.0, "error", 0, COMM)
    assert describe(left, rig.sup) == (
        logging.ERROR,
        "unit left: error +CAN_COMM_ERROR (CAN communication error)",
    )


def test_status_says_whether_each_robot_may_move_naming_the_drive() -> None:
    rig = driven()
    got = lines(rig)
    assert got["robot left"] == "robot left: READY"
    rig.drive("right").silent = True
    rig.run(1.5)
    got = lines(rig)
    assert got["robot right"].startswith("robot right: not ready: right: offline")


def test_a_drive_of_the_other_generation_is_said_held_in_status_and_the_tui() -> None:
    from abh3_supervisor.clients.mirror import Mirror
    from abh3_supervisor.clients.tui.model import hold_lines, holds

    faulty = TWO_UNITS.replace(
        "simulate: true}", "simulate: {faults: [{kind: wrong_protocol, unit: right}]}}"
    )
    rig = Rig(parse_config(faulty, "two.yaml"))
    rig.run(0.5)
    got = lines(rig)
    assert "HELD: answers as a 2021 drive, the file says 2023" in got["right"]
    assert "HELD" not in got["left"]
    mirror = Mirror.of(rig.config)
    mirror.apply(supervisor_state(rig.sup, {}))
    assert "HELD" in " ".join(holds(mirror.units["right"]))
    assert any("answers as a 2021 drive" in line for _, line in hold_lines(mirror.units["right"]))
