"""The overview as one fixed-width text that fits the terminal's width.

An order of magnitude cheaper to render than a table widget, so the UI thread leaves the
GIL to the buses. Columns never wrap: the widest layout that fits is used, and below it
the least important columns are left out (the unit tab shows everything); unit names are
whole where they fit beside the columns that matter, else abbreviated (the selected one
is then named in full under the table). Every value of an axis carries its letter (Y/X
or A/B, model.axes), so whichever columns are left, none means one thing on one row and
another on the next. Faults are named on a line of their own under their unit, wrapping
between names only, and so is what holds a unit (another host, the settings check) or
that its drive no longer answers. Once the state is no longer live (the service gone or
silent) every row is dimmed and says so, with its age.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from rich.text import Text

from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.model import (
    ALARM_MARK,
    DIFFERS,
    ERROR_MARK,
    HELD,
    HOST_STOP,
    UNKNOWN,
    age,
    fault_names,
    hold_lines,
    overview_row,
    silence_line,
)


@dataclass(frozen=True)
class Column:
    key: str
    header: str
    width: int
    priority: int  # the lowest goes first when the width does not suffice
    right: bool = False


COLUMNS = {
    c.key: c
    for c in (
        Column("unit", "unit", 10, 100),
        Column("state", "state", 7, 95),
        Column("proto", "gen", 4, 30),
        Column("servo", "servo", 8, 90),
        Column("start", "start", 8, 90),
        Column("cmd", "command", 17, 85, right=True),
        Column("fbk", "feedback min⁻¹", 17, 85, right=True),
        Column("fbk A/B", "feedback min⁻¹", 17, 80, right=True),
        Column("fbk Y/X", "feedback min⁻¹", 17, 80, right=True),
        Column("current", "current %", 15, 60, right=True),
        Column("load", "load %", 11, 55, right=True),
        Column("supply", "supply V", 11, 20, right=True),
        Column("faults", "faults", 7, 75),
        Column("rate", "rate Hz", 10, 50, right=True),
    )
}
# the full layout (feedback in both models), and the one for narrow terminals (feedback
# in each unit's own model)
WIDE = [
    "unit", "state", "servo", "start", "cmd", "fbk A/B", "fbk Y/X", "current", "load",
    "supply", "rate", "faults",
]  # fmt: skip
NARROW = ["unit", "state", "servo", "start", "cmd", "fbk", "current", "load", "rate", "faults"]
GAP = 1


UNIT_MIN = 10  # "▶ " and 8 characters of a name: below, names are abbreviated
UNIT_FLOOR = 8  # narrower still before the fault column goes (80 columns less a scrollbar)
NAME_MAX = 24  # the unit column grows with the longest name up to this
FAULTS_MAX = 17  # the fault column takes what is left of the width up to this
KEEP = 75  # columns at or above this priority stay while names are abbreviated (faults)


def fit(width: int, name_width: int = UNIT_MIN - 2) -> list[Column]:
    """The columns to show in ``width`` characters, for names up to ``name_width``
    characters long: every name in full where the columns that matter fit beside it
    (feedback, current, load and rates give way first), otherwise abbreviated (the
    unit column at least ``UNIT_MIN``); the fault column widens into what is left."""
    full = max(UNIT_MIN, 2 + min(name_width, NAME_MAX))
    for layout in (WIDE, NARROW):
        columns = _columns(layout, full)
        if _width(columns) <= width:
            return _widen(columns, width)
    columns = _columns(NARROW, full)
    while _width(columns) > width and min(c.priority for c in columns) < KEEP:
        columns.remove(min(columns, key=lambda c: c.priority))
    if _width(columns) > width:  # the names give way before any column that matters
        unit = columns[0]
        columns[0] = replace(unit, width=max(UNIT_FLOOR, unit.width - (_width(columns) - width)))
    while len(columns) > 1 and _width(columns) > width:
        columns.remove(min(columns, key=lambda c: c.priority))
    return _widen(columns, width)


def _columns(layout: list[str], unit_width: int) -> list[Column]:
    return [replace(COLUMNS[k], width=unit_width) if k == "unit" else COLUMNS[k] for k in layout]


def _widen(columns: list[Column], width: int) -> list[Column]:
    spare = width - _width(columns)
    return [
        replace(c, width=min(FAULTS_MAX, c.width + spare)) if c.key == "faults" else c
        for c in columns
    ]


def _width(columns: list[Column]) -> int:
    return sum(c.width for c in columns) + GAP * (len(columns) - 1)


def _cell(column: Column, value: str) -> str:
    value = value[: column.width]
    return f"{value:>{column.width}}" if column.right else f"{value:<{column.width}}"


def words_in(value: str, width: int) -> str:
    """As many whole words as fit in ``width``, then `` …`` if any are left out (the fault
    column: the lines under the unit name them all)."""
    if len(value) <= width:
        return value
    words = value.split(" ")
    while len(words) > 1 and len(" ".join(words)) + 2 > width:
        words.pop()
    return " ".join(words)[: width - 2] + " …"


def abbreviate(names: list[str], room: int) -> dict[str, str]:
    """Each name in at most ``room`` characters, and no two alike: a name that does not
    fit keeps its start and an ellipsis (``left_drive`` in 8: ``left_dr…``), and where
    that leaves two alike, its end too (``wheel_front_1`` and ``wheel_front_2``:
    ``whee…t_1``, ``whee…t_2``)."""
    if all(len(n) <= room for n in names) or room < 3:
        return {n: n[:room] for n in names}
    middle = (room - 1) // 2
    for tail in dict.fromkeys([0, middle, *range(1, room - 1)]):
        head = room - 1 - tail
        short = {
            n: n if len(n) <= room else n[:head] + "…" + (n[-tail:] if tail else "") for n in names
        }
        if len(set(short.values())) == len(names):
            return short
    return {n: n[: room - 1] + "…" if len(n) > room else n for n in names}


def _style(key: str, value: str, selected: bool) -> str:
    if key == "state" and value == "OFFLINE":
        return "bold red"
    if key == "faults" and value != "–":
        severe = any(mark in value for mark in (ERROR_MARK, HOST_STOP, HELD))
        return "bold red" if severe else "yellow"
    if key in ("servo", "start") and value.endswith("!"):
        return "bold yellow"
    if key in ("servo", "start") and value == UNKNOWN:
        return "dim"
    if key == "unit" and selected:
        return "reverse"
    return ""


LEGEND = (
    "\nY/X travel/turn, A/B motors (velocity_model) · min⁻¹, % in torque mode\n"
    "servo/start as the drive reports them: ! not as commanded, ? not reported\n"
    f"faults: {ERROR_MARK} errors, {ALARM_MARK} alarms, {HOST_STOP}/{HELD}/{DIFFERS}: "
    "each said under its unit"
)
LINE_STYLE = {"error": "bold red", "alarm": "yellow"}


def robot_lines(sup: Mirror, names: list[str]) -> list[tuple[str, str | None]]:
    """Each robot of these units with whether it may move: ``robot agv READY`` or ``robot
    agv not ready`` and why, naming the drive (o switches the selected unit's robot)."""
    lines = []
    for robot, why in sup.robots.items():
        config = sup.config.robots.get(robot)
        if config is not None and not any(u in names for u in config.units):
            continue
        lines.append((f"robot {robot} READY" if why is None else f"robot {robot} not ready", why))
    return lines


def render(
    sup: Mirror,
    names: list[str],
    selected: int,
    width: int,
    stale: float | None = None,
    arrows: str | None = None,
) -> Text:
    """``stale``: how old the state is once it is no longer live (None: live);
    ``arrows``: what the arrow keys drive, said under the table."""
    columns = fit(width, max(map(len, names), default=0))
    room = next((c.width for c in columns if c.key == "unit"), UNIT_MIN) - 2
    short = abbreviate(names, room)
    text = Text()
    if stale is not None:
        text.append(f"STALE: these values are {age(stale)} old, not live\n", "bold red")
    text.append(" ".join(_cell(c, c.header) for c in columns).rstrip() + "\n", style="bold")
    for bus, health in sup.buses.items():  # a bus in trouble, above its units
        if health.state != "ok":
            since = sup.t - health.since
            text.append(
                f"bus {bus}: {health.state.upper()} for {since:.0f} s: {health.detail}\n",
                "bold red",
            )
    for i, name in enumerate(names):
        row = overview_row(sup, name)
        row["unit"] = ("▶ " if i == selected else "  ") + short[name]
        if stale is not None:
            row["state"] = "stale"
        for n, column in enumerate(columns):
            if n:
                text.append(" " * GAP)
            value = row[column.key]
            if column.key == "faults":
                value = words_in(value, column.width)
            style = _style(column.key, value, i == selected)
            text.append(_cell(column, value), "dim" if stale is not None else style)
        text.append("\n")
        silence = silence_line(sup, name)
        if silence:  # its last values, greyed with their age: the row no longer shows them
            text.append(f"    {silence}\n", "dim")
        for kind, line in hold_lines(sup.units[name]):
            text.append(f"    {line}\n", LINE_STYLE[kind])
        faults = fault_names(sup, name)
        if faults:
            text.append("    ")
            for kind, bit in faults:
                mark, style = {
                    "error": (f"{ERROR_MARK} ", "bold red"),
                    "alarm": (f"{ALARM_MARK} ", "yellow"),
                }.get(kind, ("", "dim"))  # a note (a monitor's "no commands"): no mark
                text.append(f"{mark}{bit}", style)
                text.append(" ")
            text.append("\n")
    for robot, why in robot_lines(sup, names):  # the robot decision, as the service said it
        text.append(robot, "bold green" if why is None else "bold yellow")
        text.append("\n" if why is None else f": {why}\n", "dim" if why is None else "yellow")
    chosen = names[selected] if 0 <= selected < len(names) else None
    if chosen is not None and short[chosen] != chosen:  # the selected unit's whole name
        text.append(f"▶ {chosen} (selected; n/p select, 2 its details)\n", "bold")
    if arrows is not None:
        text.append(f"\n{arrows}", "bold")
    text.append(LEGEND, style="dim")
    return text
