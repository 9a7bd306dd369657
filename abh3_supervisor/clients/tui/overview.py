"""The overview as one fixed-width text that fits the terminal's width.

An order of magnitude cheaper to render than a table widget, so the UI thread leaves the
GIL to the buses. Columns never wrap: the widest layout that fits is used, and below it
the least important columns are left out (the unit tab shows everything). Every value of
an axis carries its letter (Y/X or A/B, model.axes), so whichever columns are left, none
means one thing on one row and another on the next. Faults are named on a line of their
own under their unit, wrapping between names only. Once the state is no longer live
(the service gone or silent) every row is dimmed and says so, with its age.
"""

from __future__ import annotations

from dataclasses import dataclass

from rich.text import Text

from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.model import (
    ALARM_MARK,
    ERROR_MARK,
    age,
    fault_names,
    overview_row,
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


def fit(width: int) -> list[Column]:
    """The columns to show in ``width`` characters."""
    for layout in (WIDE, NARROW):
        columns = [COLUMNS[k] for k in layout]
        if _width(columns) <= width:
            return columns
    columns = [COLUMNS[k] for k in NARROW]
    while len(columns) > 1 and _width(columns) > width:
        columns.remove(min(columns, key=lambda c: c.priority))
    return columns


def _width(columns: list[Column]) -> int:
    return sum(c.width for c in columns) + GAP * (len(columns) - 1)


def _cell(column: Column, value: str) -> str:
    value = value[: column.width]
    return f"{value:>{column.width}}" if column.right else f"{value:<{column.width}}"


def _style(key: str, value: str, selected: bool) -> str:
    if key == "state" and value == "OFFLINE":
        return "bold red"
    if key == "faults" and value != "–":
        return "bold red" if ERROR_MARK in value else "yellow"
    if key in ("servo", "start") and value.endswith("!"):
        return "bold yellow"
    if key == "unit" and selected:
        return "reverse"
    return ""


LEGEND = (
    "\nY/X travel/turn, A/B motors (each unit's velocity_model); min⁻¹, % in torque mode\n"
    "servo/start as the drive reports them; ! = not as commanded, ? = not reported yet"
)


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
    columns = fit(width)
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
        row["unit"] = ("▶ " if i == selected else "  ") + name
        if stale is not None:
            row["state"] = "stale"
        for n, column in enumerate(columns):
            if n:
                text.append(" " * GAP)
            style = _style(column.key, row[column.key], i == selected)
            text.append(_cell(column, row[column.key]), "dim" if stale is not None else style)
        text.append("\n")
        stopped = (sup.units[name].foreign or {}).get("stopped")
        if stopped:  # another host commands its drive (core/foreign.py): E clears, once quiet
            text.append(
                f"    STOPPED: {stopped} (E clears it once that host is quiet)\n", "bold red"
            )
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
    if arrows is not None:
        text.append(f"\n{arrows}", "bold")
    text.append(LEGEND, style="dim")
    return text
