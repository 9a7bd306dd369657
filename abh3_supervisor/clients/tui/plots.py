"""Bar plots of the last WINDOW_S seconds, as text: each with its name, unit, current
value and scale (min … max), bars drawn from zero so a steady value is a full bar and a
negative one hangs from the zero line; while the drive does not answer, a gap."""

from __future__ import annotations

import math
from collections.abc import Sequence

from rich.text import Text

from abh3_supervisor.clients.mirror import UnitView
from abh3_supervisor.clients.tui.model import (
    SERIES,
    WINDOW_S,
    Trace,
    fmt,
    series_label,
    series_unit,
)

UP = " ▁▂▃▄▅▆▇█"  # eighths of a cell, filled from the bottom
DOWN = " ▔▔▀▀▀██"  # from the top: Unicode has fewer steps that way
LABEL = 28
STYLES = {"cmd": "cyan", "fbk": "green", "current": "magenta", "load": "yellow"}


def columns(samples: Sequence[tuple[float, float]], now: float, width: int) -> list[float | None]:
    """The latest value in each of ``width`` equal slices of the window, held over slices
    without a sample (None before the first)."""
    out: list[float | None] = [None] * width
    start = now - WINDOW_S
    for t, value in samples:
        if t < start:
            continue
        i = min(width - 1, int((t - start) / WINDOW_S * width))
        out[i] = value
    held: float | None = None
    for i, slot in enumerate(out):
        if slot is not None and math.isnan(slot):  # the drive did not answer: a gap
            held = out[i] = None
        else:
            held = out[i] = slot if slot is not None else held
    return out


def bars(values: list[float | None], lo: float, hi: float, height: int) -> list[str]:
    """``height`` lines, top first; zero sits on a cell boundary, bars grow away from it."""
    span = hi - lo or 1.0
    zero = round((0.0 - lo) / span * height)  # rows below the zero line
    lines = [[" "] * len(values) for _ in range(height)]
    for x, v in enumerate(values):
        if v is None:
            continue
        top = (v - lo) / span * height  # the value's height in rows
        for r in range(height):  # r: row from the bottom
            if v >= 0 and r >= zero:
                fill = min(1.0, max(0.0, top - r))
                ch = UP[round(fill * 8)]
            elif v < 0 and r < zero:
                fill = min(1.0, max(0.0, (r + 1) - top))
                ch = DOWN[min(7, round(fill * 7))] if fill < 1.0 else "█"
            else:
                continue
            lines[height - 1 - r][x] = ch
    return ["".join(line) for line in lines]


def render(unit: UnitView, trace: Trace, now: float, width: int, height: int) -> Text:
    """Every series of one unit, each ``height`` rows (at least 2) with its label."""
    height = max(2, height)
    plot_width = max(10, width - LABEL - 1)
    text = Text()
    for key, _ in SERIES:
        samples = list(trace.series[key])  # one C call: the sampler appends on this thread
        values = columns(samples, now, plot_width)
        seen = [v for v in values if v is not None]
        lo, hi = min([0.0, *seen]), max([0.0, *seen])
        current = samples[-1][1] if samples and not math.isnan(samples[-1][1]) else None
        label = [
            f"{series_label(unit, key)} [{series_unit(unit, key)}]",
            f"now {fmt(current)}",
            f"{fmt(lo)} … {fmt(hi)}",
        ]
        if height == 2:
            label = [label[0], f"{label[1]} · {label[2]}"]
        style = STYLES[key.split()[0]]
        for row, line in enumerate(bars(values, lo, hi, height)):
            head = label[row] if row < len(label) else ""
            text.append(f"{head[:LABEL]:<{LABEL}} ", "bold" if row == 0 else "dim")
            text.append(line + "\n", style)
    text.append(f"last {WINDOW_S:g} s, newest on the right; scale from zero", "dim")
    return text
