"""What the screens show, computed from a :class:`Mirror` without any Textual: testable alone.

State is shown as the drive reports it (its control word) wherever the drive reports
it; a ``!`` marks a switch the drive reports other than it is commanded. What a drive
reported is shown only while it answers: an offline drive's feedback, currents and
supplies are blanked (its last feedback is said with its age) and its switches are ``?``.

One axis vocabulary: the drive's A/Y and B/X channels (command, current) are named by
the unit's velocity model — Y/X for ``travel``, A/B for ``motor`` — and every value
carries its letter, so no column or series changes meaning from one unit to the next.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from abh3_supervisor.clients.mirror import Mirror, UnitView
from abh3_supervisor.config.model import ControlMode, Role, VelocityModel
from abh3_supervisor.core import readouts
from abh3_supervisor.core.planner import BusPlan
from abh3_supervisor.protocol import flags, frames

WINDOW_S = 30.0  # what the plots show
SET, CLEAR = "●", "○"  # a set bit has a symbol as well as a colour
ERROR_MARK, ALARM_MARK = "✖", "▲"
# the overview's fault column beside the counts: what keeps a unit from moving that is
# no error bit of its drive (each explained on a line under the unit)
HOST_STOP = "HOST"  # stopped: another host commands its drive (core/foreign.py)
HELD = "HELD"  # held at its idle word by the settings check (core/verify.py)
DIFFERS = "≠YAML"  # its drive's CAN settings differ from the file, not held (verify: warn)
UNKNOWN = "?/?"  # a switch of a drive that no longer answers


def onoff(value: bool) -> str:
    return "ON" if value else "off"


def fmt(value: float | None, digits: int = 1) -> str:
    return "–" if value is None else f"{value + 0.0:.{digits}f}"  # + 0.0: never "-0.0"


def pair(a: float | None, b: float | None, digits: int = 1, width: int = 7) -> str:
    """Two numbers, each right-aligned in ``width``: columns line up under a header."""
    return f"{fmt(a, digits):>{width}} {fmt(b, digits):>{width}}"


def axes(unit: UnitView) -> tuple[str, str]:
    """The letters of the unit's A/Y and B/X channels in its velocity model."""
    return ("Y", "X") if unit.cfg.velocity_model is VelocityModel.TRAVEL else ("A", "B")


def labelled(
    letters: tuple[str, str],
    a: float | None,
    b: float | None,
    digits: int = 1,
    width: int = 7,
    unit: str = "",
) -> str:
    """Two numbers, each after its axis letter (``Y  300.0 X   20.0``), aligned in columns."""
    return (
        f"{letters[0]}{fmt(a, digits):>{width}}{unit} {letters[1]}{fmt(b, digits):>{width}}{unit}"
    )


def spoken(letters: tuple[str, str], a: float | None, b: float | None, digits: int = 1) -> str:
    """The same in running text: ``Y 300.0 X 20.0``."""
    return f"{letters[0]} {fmt(a, digits)} {letters[1]} {fmt(b, digits)}"


def model_name(unit: UnitView) -> str:
    travel = unit.cfg.velocity_model is VelocityModel.TRAVEL
    return "travel: Y travel, X turn" if travel else "motor: A, B motors"


def age(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 10 else f"{seconds:.0f} s"


def status_record(unit: UnitView, packet: int) -> frames.Broadcast | None:
    return unit.status.get(packet)


def reported(unit: UnitView) -> int | None:
    """The control word as the drive reports it (None until it has)."""
    return unit.words.get("control")


def answering(unit: UnitView) -> bool:
    """The drive answers now, so what it reports is live (offline or not heard yet: not)."""
    return unit.online is True


def silent_for(sup: Mirror, unit: UnitView) -> float | None:
    """How old the drive's last feedback is (None: it never sent any)."""
    fb = unit.feedback
    return None if fb is None else max(0.0, sup.t - fb.t)


def switch(unit: UnitView, mask: flags.Pair) -> str:
    """``ON/off`` per axis as the drive reports it; ``!`` where the command differs,
    ``?`` when the drive has not reported it (the command is shown then), ``?/?`` when it
    no longer answers (its last report may no longer hold)."""
    if unit.online is False:
        return UNKNOWN
    control = reported(unit)
    word = unit.inputs if control is None else control
    text = f"{onoff(bool(word & mask.ay))}/{onoff(bool(word & mask.bx))}"
    if control is None:
        return text + "?"
    differs = unit.cfg.role is Role.COMMAND and (control ^ unit.inputs) & mask.both
    return text + ("!" if differs else "")


def unit_of(unit: UnitView) -> str:
    return "%" if unit.setpoint.kind is ControlMode.CURRENT else "min⁻¹"


def model_feedback(unit: UnitView) -> tuple[float | None, float | None]:
    """Velocity feedback in the unit's own model's axes."""
    fb = unit.feedback
    if fb is None:
        return None, None
    travel = unit.cfg.velocity_model is VelocityModel.TRAVEL
    return (fb.vel_y, fb.vel_x) if travel else (fb.vel_a, fb.vel_b)


def holds(unit: UnitView) -> list[str]:
    """The fault column's words for what keeps the unit from moving or needs a look that
    is no error bit: stopped for another host, held by the settings check, settings that
    differ from the file."""
    shown = [HOST_STOP] if (unit.foreign or {}).get("stopped") else []
    verify = unit.verify or {}
    if verify.get("held") or unit.other_generation:
        shown.append(HELD)
    elif verify.get("state") == "mismatch":
        shown.append(DIFFERS)
    return shown


def hold_lines(unit: UnitView) -> list[tuple[str, str]]:
    """(style key, text) per :func:`holds` word: what it is and how it ends."""
    lines = []
    stopped = (unit.foreign or {}).get("stopped")
    if stopped:  # E clears it, and the service does so only once that host is quiet
        lines.append(("error", f"STOPPED: {stopped} (E clears it once that host is quiet)"))
    if unit.other_generation:  # identity before energy: only the probe goes to it
        lines.append(("error", f"HELD: {unit.other_generation}"))
    verify = unit.verify or {}
    if verify.get("held"):
        lines.append(("error", f"HELD: {verify['held']}"))
    elif verify.get("state") == "mismatch":
        lines += [
            ("alarm", f"{DIFFERS} (verify: warn, so it runs): {row['text']}")
            for row in verify.get("mismatches", ())
        ]
    return lines


def silence_line(sup: Mirror, name: str) -> str | None:
    """Under an offline unit: how long it has not answered and its last feedback, which
    the row no longer shows."""
    unit = sup.units[name]
    if unit.online is not False:
        return None
    quiet = silent_for(sup, unit)
    if quiet is None:
        return "no answer: what it reports is unknown"
    last = spoken(axes(unit), *model_feedback(unit))
    return f"no answer for {age(quiet)}; its last feedback: {last} min⁻¹"


def unit_state(unit: UnitView) -> str:
    return {True: "online", False: "OFFLINE", None: "waiting"}[unit.online]


def overview_row(sup: Mirror, name: str) -> dict[str, str]:
    """The overview's cells. What the drive reports (feedback, currents, load,
    supplies) only while it answers: blank ``–`` otherwise, never a value it sent before."""
    unit = sup.units[name]
    live = answering(unit)
    fb = unit.feedback if live else None
    brd3 = status_record(unit, 3) if live else None
    brd5 = status_record(unit, 5) if live else None
    error, alarm = unit.words.get("error", 0), unit.words.get("alarm", 0)
    letters = axes(unit)
    role = unit.cfg.role  # a monitor's "no commands" bit is a note, not a fault
    faults = " ".join(
        holds(unit)
        + [
            f"{mark}{count}"
            for mark, word in ((ERROR_MARK, error), (ALARM_MARK, alarm))
            if (count := len(readouts.read_faults(role, word).names))
        ]
    )
    sp = unit.setpoint
    current_mode = sp.kind is ControlMode.CURRENT
    return {
        "unit": name,
        "state": unit_state(unit),
        "proto": unit.cfg.protocol.value,
        "mode": f"{unit.setpoint.kind.value[:3]} {unit.cfg.velocity_model.value}",
        "servo": switch(unit, unit.layout.servo),
        "start": switch(unit, unit.layout.start),
        "cmd": (
            labelled(letters, sp.ay, sp.bx, 2, 6, "%")
            if current_mode
            else labelled(letters, sp.ay, sp.bx)
        ),
        "fbk": labelled(letters, *(model_feedback(unit) if live else (None, None))),
        "fbk A/B": labelled(("A", "B"), fb.vel_a if fb else None, fb.vel_b if fb else None),
        "fbk Y/X": labelled(("Y", "X"), fb.vel_y if fb else None, fb.vel_x if fb else None),
        "current": (
            labelled(letters, brd3.cur_cmd_ay, brd3.cur_cmd_bx, 2, 6)
            if isinstance(brd3, frames.Brd3)
            else labelled(letters, None, None, 2, 6)
        ),
        "load": (  # per motor, whatever the model
            labelled(("A", "B"), brd3.load_a, brd3.load_b, 0, 4)
            if isinstance(brd3, frames.Brd3)
            else labelled(("A", "B"), None, None, 0, 4)
        ),
        "supply": (
            pair(brd5.main_volt, brd5.control_volt, 1, 5)
            if isinstance(brd5, frames.Brd5)
            else pair(None, None, 1, 5)
        ),
        "faults": faults or "–",
        "rate": f"{unit.stats.rate_hz:5.1f}/{unit.stats.requested_rate_hz:g}",
    }


def fault_names(sup: Mirror, name: str) -> list[tuple[str, str]]:
    """(mark, bit name) of every error and alarm bit set on a unit; bits normal for its
    role come last, once, as ("note", what they mean): a monitor's CAN_COMM_ERROR is
    ("note", "no commands (monitor)")."""
    unit = sup.units[name]
    role = unit.cfg.role
    faults = {word: readouts.read_faults(role, unit.words.get(word)) for word in ("error", "alarm")}
    notes = dict.fromkeys(note for f in faults.values() for note in f.notes)
    return [(word, bit) for word, f in faults.items() for bit in f.names] + [
        ("note", note) for note in notes
    ]


def flag_lines(layout: flags.Layout, word_name: str, value: int | None) -> list[tuple[bool, str]]:
    """Every bit of a word in the unit's generation, set or not: (set, "● bit name")."""
    word = layout.words[word_name]
    value = value or 0
    return [
        (bool(value & b.mask), f"{SET if value & b.mask else CLEAR} {b.bit:>2} {b.name}")
        for b in word.bits
    ]


def fault_lines(
    error: int | None, alarm: int | None, role: Role = Role.COMMAND
) -> list[tuple[str, str]]:
    """Every error/alarm bit: (style key, "✖▲ bit name") — error and alarm share a word.
    A set bit normal for the unit's role is ("note", "·· bit name: what it means")."""
    error, alarm = error or 0, alarm or 0
    lines = []
    for b in flags.FAULT.bits:
        e, a = bool(error & b.mask), bool(alarm & b.mask)
        note = readouts.fault_note(role, b) if e or a else None
        if note is not None:
            lines.append(("note", f"·· {b.bit:>2} {b.name}: {note}"))
            continue
        marks = (ERROR_MARK if e else "·") + (ALARM_MARK if a else "·")
        lines.append(("error" if e else "alarm" if a else "", f"{marks} {b.bit:>2} {b.name}"))
    return lines


def verify_fields(verify: dict[str, Any] | None) -> list[str]:
    """The drive's CAN settings against the YAML (core/verify.py), as the service sent them:
    its state, each mismatch in full, and why a ``verify: refuse`` unit is held."""
    if verify is None:
        return []
    state = verify["state"]
    if state == "mismatch":
        shown = [f"drive settings MISMATCH: {row['text']}" for row in verify["mismatches"]]
    elif state == "not verified":  # no reason: it was not tried (yet)
        reason = verify.get("reason")
        shown = [f"drive settings not verified ({reason})" if reason else "drive settings unread"]
    else:
        shown = [f"drive settings {state}"]
    if verify.get("held"):
        shown.append(f"HELD: {verify['held']}")
    return shown


def foreign_fields(foreign: dict[str, Any] | None) -> list[str]:
    """Other hosts on the unit's drive (core/foreign.py), as the service sent them: the
    stop they caused, and each host with its frames."""
    if not foreign:
        return []
    shown = [f"STOPPED: {foreign['stopped']}"] if foreign.get("stopped") else []
    return shown + [host["text"] for host in foreign.get("hosts", ())]


def detail_fields(
    sup: Mirror, name: str, firmware: str | None = None, stale: float | None = None
) -> list[str]:
    """The unit's figures, one field each: a field is never split across lines. ``stale``:
    how old they are when they are no longer live."""
    unit = sup.units[name]
    st = unit.stats
    sp, fb = unit.setpoint, unit.feedback
    letters = axes(unit)
    quiet = silent_for(sup, unit)
    # a drive that does not answer: its last values, each with its age
    old = "" if answering(unit) or quiet is None else f" ({age(quiet)} old)"
    fields = [f"STALE {age(stale)}"] if stale is not None else []
    fields += [
        f"unit {name}",
        *([f"{unit_state(unit)}: {line}"] if (line := silence_line(sup, name)) else []),
        f"velocity model {model_name(unit)}",
        f"cmd {spoken(letters, sp.ay, sp.bx, 2 if sp.kind is ControlMode.CURRENT else 1)} "
        + unit_of(unit),
        f"fbk {spoken(('Y', 'X'), fb.vel_y, fb.vel_x) if fb else '–'} min⁻¹{old}",
        f"fbk {spoken(('A', 'B'), fb.vel_a, fb.vel_b) if fb else '–'} min⁻¹{old}",
        f"firmware {firmware or '–'}",
        f"abh3_id {unit.cfg.abh3_id}",
        f"host {unit.cfg.host_id}",
        f"bus {unit.cfg.bus}",
        f"group {unit.cfg.brd_group}",
        f"protocol {unit.cfg.protocol}",
        f"role {unit.cfg.role.value}",
        f"rate {st.rate_hz:.1f}/{st.requested_rate_hz:g} Hz",
        f"exchanges {st.replies}/{st.commands_sent}",
        f"timeouts {st.timeouts}",
        f"send errors {st.send_errors}",
        f"rtt p50 {fmt(st.rtt_p50_ms, 2)} ms",
        f"rtt p99 {fmt(st.rtt_p99_ms, 2)} ms",
        f"status packets {st.broadcasts}",
        f"malformed {st.malformed}",
        f"gaps {st.gaps}",
        *verify_fields(unit.verify),
        *foreign_fields(unit.foreign),
    ]
    b3, b4, b5 = status_record(unit, 3), status_record(unit, 4), status_record(unit, 5)
    b6 = status_record(unit, 6)
    if unit.online is False and (b3 or b4 or b5 or b6):
        fields.append("status as last reported, before it went silent")
    if isinstance(b3, frames.Brd3):
        fields += [
            f"current {spoken(letters, b3.cur_cmd_ay, b3.cur_cmd_bx, 2)} %",
            f"load {spoken(('A', 'B'), b3.load_a, b3.load_b, 0)} %",
        ]
    if isinstance(b4, frames.Brd4):
        fields += [f"pulses A {b4.pulse_a}", f"pulses B {b4.pulse_b}"]
    if isinstance(b5, frames.Brd5):
        fields += [
            f"analog0 {b5.analog0:.2f} V",
            f"analog1 {b5.analog1:.2f} V",
            f"main {b5.main_volt:.1f} V",
            f"control {b5.control_volt:.1f} V",
        ]
    if isinstance(b6, frames.Brd6):
        fields += [f"monitor0 {b6.monitor0:.4f}", f"monitor1 {b6.monitor1:.4f}"]
    return fields


def pack(fields: list[str], width: int, sep: str = " · ") -> list[str]:
    """Fields joined into lines of at most ``width``, breaking only between fields."""
    lines: list[str] = []
    line = ""
    for f in fields:
        candidate = f"{line}{sep}{f}" if line else f
        if line and len(candidate) > width:
            lines.append(line)
            line = f
        else:
            line = candidate
    if line:
        lines.append(line)
    return lines


# ---------------------------------------------------------------- plots

# keyed by the drive's channels (AY, BX) or motors (A, B); shown by series_label
SERIES = (
    ("cmd AY", "velocity or current command, A/Y"),
    ("cmd BX", "velocity or current command, B/X"),
    ("fbk AY", "velocity feedback, A/Y"),
    ("fbk BX", "velocity feedback, B/X"),
    ("current AY", "current command, A/Y [%]"),
    ("current BX", "current command, B/X [%]"),
    ("load A", "load, motor A [%]"),
    ("load B", "load, motor B [%]"),
)


REPORTED = ("fbk AY", "fbk BX", "current AY", "current BX", "load A", "load B")  # by the drive
GAP = math.nan  # a sample while the drive does not answer: nothing is known


@dataclass
class Trace:
    """One unit's recent values, (time, value) per series, the last WINDOW_S seconds."""

    series: dict[str, deque[tuple[float, float]]] = field(
        default_factory=lambda: {key: deque() for key, _ in SERIES}
    )

    def add(self, t: float, key: str, value: float) -> None:
        samples = self.series[key]
        samples.append((t, value))
        while samples and samples[0][0] < t - WINDOW_S:
            samples.popleft()


def series_unit(unit: UnitView, key: str) -> str:
    if key.startswith("cmd"):
        return unit_of(unit)
    return "min⁻¹" if key.startswith("fbk") else "%"


def series_label(unit: UnitView, key: str) -> str:
    """The series' name in the unit's terms: a channel by its velocity model's letter."""
    name, axis = key.split()
    channel = {"AY": 0, "BX": 1}.get(axis)
    return key if channel is None else f"{name} {axes(unit)[channel]}"


class Sampler:
    """Keeps the recent history the plots draw, one sample per refresh."""

    def __init__(self, sup: Mirror) -> None:
        self.sup = sup
        self.traces = {name: Trace() for name in sup.units}

    def sample(self) -> None:
        now = self.sup.t
        for name, unit in self.sup.units.items():
            trace = self.traces[name]
            sp, fb = unit.setpoint, unit.feedback
            travel = unit.cfg.velocity_model is VelocityModel.TRAVEL
            trace.add(now, "cmd AY", sp.ay)
            trace.add(now, "cmd BX", sp.bx)
            if not answering(unit):  # a gap in its plots, not its last values held
                for key in REPORTED:
                    trace.add(now, key, GAP)
                continue
            if fb is not None:
                trace.add(now, "fbk AY", fb.vel_y if travel else fb.vel_a)
                trace.add(now, "fbk BX", fb.vel_x if travel else fb.vel_b)
            brd3 = status_record(unit, 3)
            if isinstance(brd3, frames.Brd3):
                trace.add(now, "current AY", brd3.cur_cmd_ay)
                trace.add(now, "current BX", brd3.cur_cmd_bx)
                trace.add(now, "load A", brd3.load_a)
                trace.add(now, "load B", brd3.load_b)


# ---------------------------------------------------------------- bus view


@dataclass
class BusSample:
    frames: int = 0
    t: float = 0.0


def bus_fields(
    sup: Mirror, plans: dict[str, BusPlan], last: dict[str, BusSample]
) -> list[list[str]]:
    """Per bus and per unit on it, the fields of one line (frames/s and load % since the
    previous call, error counts)."""
    lines = []
    for name, pump in sup.buses.items():
        now = sup.t
        total = pump.frames_sent + pump.frames_received
        prev = last.get(name, BusSample(total, now))
        rate = (total - prev.frames) / (now - prev.t) if now > prev.t else 0.0
        last[name] = BusSample(total, now)
        p = plans[name]
        bits_per_frame = p.bits_per_s / p.frames_per_s if p.frames_per_s else 0.0
        load = 100 * rate * bits_per_frame / p.bitrate
        lines.append(
            [
                f"bus {name}",
                f"interface {pump.state}",
                f"{rate:.0f} frames/s",
                f"≈{load:.1f} % of {p.bitrate} bit/s",
                f"planned {p.load_percent:.1f} %",
                f"send errors {pump.send_errors}",
                f"bus errors {pump.bus_errors}",
            ]
        )
        for unit, view in sup.units.items():
            if view.cfg.bus != name:
                continue
            st = view.stats
            lines.append(
                [
                    f"  {unit}",
                    f"timeouts {st.timeouts}",
                    f"send errors {st.send_errors}",
                    f"replies {st.replies}",
                    f"status {st.broadcasts}",
                    f"malformed {st.malformed}",
                    f"gaps {st.gaps}",
                ]
            )
    return lines
