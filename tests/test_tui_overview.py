"""What the overview (and the unit tab) claims about a drive, on the fake clock: nothing a
drive that no longer answers said before is shown as if it still held, what holds a unit
that is no error bit of its drive is in the fault column, and unit names fit at 80
columns. Found by a new-user trial (an OFFLINE drive showed `-382.0` and `ON/ON`, the
fault column `–` for a held unit, names cut at `left_dri`)."""

from __future__ import annotations

import re

from abh3_supervisor.clients.tui import overview, plots
from abh3_supervisor.clients.tui.model import (
    DIFFERS,
    HELD,
    HOST_STOP,
    UNKNOWN,
    Sampler,
    detail_fields,
    overview_row,
)
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.verify import DriveCheck, State, Verification
from tests.support.foreign_host import TimelineHost
from tests.support.rig import TWO_UNITS, Rig, present, set_velocity
from tests.support.tui import mirror_of, snapshot_rig

REPORTED = ("fbk", "fbk A/B", "fbk Y/X", "current", "load", "supply")  # by the drive


def table_lines(text: str, names: list[str]) -> list[str]:
    """The header and the unit rows of a rendered overview (not the lines under them)."""
    lines = text.splitlines()
    return [lines[0]] + [line for line in lines if line[2:].startswith(tuple(names))]


def test_an_offline_drive_shows_no_value_it_sent_before() -> None:
    """left drives (Y 300, X 20) with SERVO and START on, then its drive stops answering:
    its feedback, currents, load and supplies are blanked, its switches unknown, and its
    last feedback is said under it with its age; the unit tab gives each its age."""
    rig = snapshot_rig()
    rig.drive("left").silent = True
    rig.run(2.0)
    mirror = mirror_of(rig)
    assert mirror.units["left"].online is False
    row = overview_row(mirror, "left")
    assert row["state"] == "OFFLINE"
    assert row["servo"] == row["start"] == UNKNOWN  # not ON/ON: it may have tripped since
    for key in REPORTED:
        assert not re.search(r"\d", row[key]), (key, row[key])  # no number, only letters and –
    assert re.fullmatch(r"Y +– X +–", row["fbk Y/X"])  # the axis letters stay
    for width in (80, 120, 160):
        text = overview.render(mirror, ["left", "right"], 0, width).plain
        (left,) = [line for line in table_lines(text, ["left"]) if "left" in line]
        assert "300.0" not in left and "ON/ON" not in left, (width, left)
        said = re.search(r"no answer for ([\d.]+) s; its last feedback: Y 300.0 X 20.0", text)
        assert said and float(said[1]) >= 1.0, (width, text)
    # the answering unit is untouched
    assert overview_row(mirror, "right")["fbk"] != overview_row(mirror, "left")["fbk"]
    assert overview_row(mirror, "right")["state"] == "online"
    fields = detail_fields(mirror, "left")
    assert any(f.startswith("OFFLINE: no answer for ") for f in fields)
    assert any(re.fullmatch(r"fbk Y 300\.0 X 20\.0 min⁻¹ \([\d.]+ s old\)", f) for f in fields)
    assert "status as last reported, before it went silent" in fields
    # the plots: a gap, not the last value held; "now" unknown
    sampler = Sampler(mirror)
    sampler.sample()
    shown = plots.render(mirror.units["left"], sampler.traces["left"], mirror.t, 80, 2).plain
    assert "fbk Y [min⁻¹]" in shown and "now –" in shown
    # and it answers again: every value is back
    rig.drive("left").silent = False
    rig.run(1.0)
    mirror = mirror_of(rig)
    assert overview_row(mirror, "left")["servo"] != UNKNOWN
    assert "no answer" not in overview.render(mirror, ["left", "right"], 0, 80).plain


def test_a_drive_not_heard_yet_shows_the_command_with_a_question_mark() -> None:
    rig = Rig(parse_config(TWO_UNITS, "t.yaml"))
    mirror = mirror_of(rig)  # nothing run: no drive has answered
    row = overview_row(mirror, "left")
    assert row["state"] == "waiting" and row["servo"] == "off/off?"
    assert all(not re.search(r"\d", row[key]) for key in REPORTED)
    assert "no answer" not in overview.render(mirror, ["left", "right"], 0, 80).plain


HELD_CONFIG = """
buses:
  b: {interface: virtual, channel: t, simulate: {params: {left: {0x4117: 750}, right: {0x4117: 750}}}}
units:
  - {name: left, abh3_id: 1, verify: refuse}
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor}
"""


def verified(rig: Rig, unit: str) -> Verification:
    """The start-up check of ``unit``'s drive on the fake clock, as the supervisor keeps it."""
    out: list[Verification] = []
    cfg = rig.config.units[unit]
    DriveCheck(rig.config, cfg, rig.scheduler.params[unit], out.append).start()
    rig.run(0.5)
    (outcome,) = out
    rig.sup.units[unit].verify = outcome
    return outcome


def test_a_settings_mismatch_and_a_hold_are_in_the_fault_column() -> None:
    """Both drives' 0x4117 reads 750 ms, the file says 500: left (verify: refuse) is held,
    right (warn) runs; the fault column says so at every width, the lines under each
    unit say what and how it ends."""
    rig = Rig(parse_config(HELD_CONFIG, "held.yaml"))
    for unit in ("left", "right"):
        assert verified(rig, unit).state is State.MISMATCH
    mirror = mirror_of(rig)
    assert overview_row(mirror, "left")["faults"] == HELD
    assert overview_row(mirror, "right")["faults"] == DIFFERS
    for width in (80, 100, 160):
        text = overview.render(mirror, ["left", "right"], 0, width).plain
        rows = table_lines(text, ["left", "right"])
        assert all(len(line) <= width for line in rows), (width, rows)
        assert rows[1].rstrip().endswith(HELD) and rows[2].rstrip().endswith(DIFFERS)
        flat = " ".join(text.split())  # the lines under a unit wrap on the screen
        assert "HELD: its drive's CAN settings differ from the file (verify: refuse): " in flat
        assert "drive 0x4117 CAN_COMMAND_ZERO_TIMEOUT = 750 ms, YAML drive_timeout_ms" in flat
        assert f"{DIFFERS} (verify: warn, so it runs): drive 0x4117" in flat
    rendered = overview.render(mirror, ["left", "right"], 0, 80)
    styles = {
        rendered.plain[span.start : span.end].strip(): str(span.style) for span in rendered.spans
    }
    assert styles[HELD] == "bold red" and styles[DIFFERS] == "yellow"


def test_a_stop_for_another_host_is_in_the_fault_column_with_the_drives_errors() -> None:
    """Another host commands left's drive: the supervisor stops the unit; the fault column
    says HOST before the error count, and at 80 columns keeps whole words."""
    rig = snapshot_rig()  # right: an error and an alarm
    rig.timeline.add(TimelineHost(3, start=rig.timeline.now + 0.1))
    rig.run(0.5)
    mirror = mirror_of(rig)
    assert overview_row(mirror, "right")["faults"] == f"{HOST_STOP} ✖1 ▲1"
    assert overview_row(mirror, "left")["faults"] == "–"
    for width, cell in ((80, f"{HOST_STOP} …"), (160, f"{HOST_STOP} ✖1 ▲1")):
        text = overview.render(mirror, ["left", "right"], 0, width).plain
        (right,) = [line for line in table_lines(text, ["right"]) if "right" in line]
        assert right.rstrip().endswith(cell), (width, right)
        assert "STOPPED: another host (0x02) commands drive 0x03" in " ".join(text.split())


LONG_NAMES = TWO_UNITS.replace("name: left", "name: left_drive").replace(
    "name: right", "name: right_drive"
)
SIMILAR_NAMES = TWO_UNITS.replace("name: left", "name: wheel_front_1").replace(
    "name: right", "name: wheel_front_2"
)


def test_unit_names_fit_at_80_columns_and_are_whole_where_they_can_be() -> None:
    for config, names in (
        (LONG_NAMES, ["left_drive", "right_drive"]),
        (SIMILAR_NAMES, ["wheel_front_1", "wheel_front_2"]),
    ):
        rig = Rig(parse_config(config, "t.yaml"))
        rig.run(1.0)
        mirror = mirror_of(rig)
        for width in (78, 80, 100, 120, 160):
            for selected in (0, 1):
                text = overview.render(mirror, names, selected, width).plain
                lines = text.splitlines()
                rows = [
                    line for line in lines if line.startswith(("▶ ", "  ")) and " online " in line
                ]
                assert len(rows) == 2 and all(len(line) <= width for line in [lines[0], *rows])
                shown = [row[2:].split(" ")[0] for row in rows]
                assert len(set(shown)) == 2, (width, shown)  # never two alike
                assert "faults" in lines[0], width  # the fault column stays
                if width >= 100:
                    assert shown == names, (width, shown)  # whole: not "left_dri"
                else:  # abbreviated: the selected one in full under the table
                    assert all("…" in s for s in shown), (width, shown)
                    assert f"▶ {names[selected]} (selected" in text
                    for full, short in zip(names, shown, strict=True):
                        head, _, tail = short.partition("…")
                        assert full.startswith(head) and full.endswith(tail)
        assert f"unit {names[0]}" in detail_fields(mirror, names[0])  # the unit tab: whole


def test_abbreviations_keep_the_end_that_tells_names_apart() -> None:
    short = overview.abbreviate(["wheel_front_1", "wheel_front_2", "base"], 8)
    assert short == {"wheel_front_1": "whee…t_1", "wheel_front_2": "whee…t_2", "base": "base"}
    assert overview.abbreviate(["left_drive", "right_drive"], 8) == {
        "left_drive": "left_dr…",
        "right_drive": "right_d…",
    }
    assert overview.abbreviate(["a", "b"], 8) == {"a": "a", "b": "b"}


def test_the_whole_name_under_the_table_is_the_selected_units() -> None:
    """An abbreviated unit that is not selected is named only by its abbreviation (and
    an offline one keeps it, with unknown switches)."""
    rig = Rig(parse_config(LONG_NAMES, "t.yaml"))
    set_velocity(rig.sup, "left_drive", 100, 0, source=present(rig.sup, "left_drive"))
    rig.run(1.0)
    rig.drive("left_drive").silent = True
    rig.run(1.0)
    text = overview.render(mirror_of(rig), ["left_drive", "right_drive"], 1, 80).plain
    assert "▶ right_drive (selected" in text and "▶ left_drive" not in text
    assert re.search(r"^  left_dr… OFFLINE \?/\? +\?/\? ", text, re.M)
