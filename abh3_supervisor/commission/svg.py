"""Inline SVG plots of a jog or a step: command vs feedback (min⁻¹) above, current (%)
below. Plain polylines whose points map linearly from the data; each panel carries its
data ranges (``data-t0``/``data-t1``/``data-y0``/``data-y1``) so a reader — or a test —
can turn the points back into the values of the JSON report."""

from __future__ import annotations

from collections.abc import Sequence
from html import escape

from abh3_supervisor.commission.model import Trace

WIDTH, PANEL, GAP, LEFT, RIGHT, TOP = 640, 150, 34, 52, 12, 18
COLOURS = {
    "command-a": "#7f7f7f",
    "command-b": "#bcbcbc",
    "feedback-a": "#1f77b4",
    "feedback-b": "#d62728",
    "current-a": "#2ca02c",
    "current-b": "#ff7f0e",
}


def _range(values: Sequence[float], floor: float) -> tuple[float, float]:
    lo, hi = min([0.0, *values]), max([0.0, *values])
    pad = max((hi - lo) * 0.08, floor)
    return lo - pad, hi + pad


def x_of(t: float, t0: float, t1: float) -> float:
    return round(LEFT + (t - t0) / (t1 - t0) * (WIDTH - LEFT - RIGHT), 2)


def y_of(v: float, y0: float, y1: float, top: float) -> float:
    return round(top + PANEL - (v - y0) / (y1 - y0) * PANEL, 2)


def _panel(
    label: str,
    top: float,
    t_range: tuple[float, float],
    series: dict[str, list[tuple[float, float]]],
    floor: float,
) -> list[str]:
    t0, t1 = t_range
    y0, y1 = _range([v for pts in series.values() for _, v in pts], floor)
    out = [
        f'<g class="panel" data-panel="{label}" data-t0="{t0!r}" data-t1="{t1!r}" '
        f'data-y0="{y0!r}" data-y1="{y1!r}" data-top="{top!r}">',
        f'<rect x="{LEFT}" y="{top}" width="{WIDTH - LEFT - RIGHT}" height="{PANEL}" '
        'fill="none" stroke="#ccc"/>',
        f'<text x="4" y="{top + 12}" font-size="11">{escape(label)}</text>',
        f'<text x="{LEFT - 4}" y="{top + 10}" font-size="10" text-anchor="end">{y1:.0f}</text>',
        f'<text x="{LEFT - 4}" y="{top + PANEL}" font-size="10" text-anchor="end">{y0:.0f}</text>',
    ]
    zero = y_of(0.0, y0, y1, top)
    out.append(f'<line x1="{LEFT}" x2="{WIDTH - RIGHT}" y1="{zero}" y2="{zero}" stroke="#eee"/>')
    for name, pts in series.items():
        if not pts:
            continue
        points = " ".join(f"{x_of(t, t0, t1)},{y_of(v, y0, y1, top)}" for t, v in pts)
        out.append(
            f'<polyline data-series="{name}" fill="none" stroke="{COLOURS[name]}" '
            f'stroke-width="1.5" points="{points}"/>'
        )
    out.append("</g>")
    return out


def _steps(rows: Sequence[tuple[float, float, float]], index: int) -> list[tuple[float, float]]:
    """A command as it is: held from one frame to the next (a staircase)."""
    out: list[tuple[float, float]] = []
    for t, *values in rows:
        v = values[index - 1]
        if out and out[-1][1] != v:
            out.append((t, out[-1][1]))
        out.append((t, v))
    return out


def plot(trace: Trace) -> str:
    times = [r[0] for rows in (trace.command, trace.feedback, trace.current) for r in rows]
    t_range = (min([0.0, *times]), max([0.1, *times]))
    velocity = {
        "command-a": _steps(trace.command, 1),
        "command-b": _steps(trace.command, 2),
        "feedback-a": [(t, a) for t, a, _ in trace.feedback],
        "feedback-b": [(t, b) for t, _, b in trace.feedback],
    }
    current = {
        "current-a": [(t, a) for t, a, _ in trace.current],
        "current-b": [(t, b) for t, _, b in trace.current],
    }
    height = TOP + 2 * PANEL + GAP + 30
    lines = [
        f'<svg width="{WIDTH}" height="{height}" '
        f'viewBox="0 0 {WIDTH} {height}" role="img" aria-label="{escape(trace.title)}">',
        *_panel("velocity min⁻¹", TOP, t_range, velocity, 10.0),
        *_panel("current %", TOP + PANEL + GAP, t_range, current, 5.0),
        f'<text x="{LEFT}" y="{height - 6}" font-size="10">0 s</text>',
        f'<text x="{WIDTH - RIGHT}" y="{height - 6}" font-size="10" text-anchor="end">'
        f"{t_range[1]:.2f} s</text>",
        _legend(height - 6),
        "</svg>",
    ]
    return "\n".join(lines)


def _legend(y: float) -> str:
    items = []
    x = LEFT + 60
    for name, colour in COLOURS.items():
        items.append(
            f'<line x1="{x}" x2="{x + 14}" y1="{y - 4}" y2="{y - 4}" stroke="{colour}" '
            f'stroke-width="2"/><text x="{x + 17}" y="{y}" font-size="10">{name}</text>'
        )
        x += 80
    return "".join(items)
