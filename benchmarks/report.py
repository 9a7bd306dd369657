"""Figures printed side by side with their baselines, as ratios, with the target verdict."""

from __future__ import annotations

import os
import platform
import statistics
import sys
from collections.abc import Callable
from dataclasses import dataclass

import can


@dataclass(frozen=True)
class Row:
    section: str
    figure: str
    ours: float
    baseline: float | None
    unit: str
    target: str = ""
    ok: bool | None = None

    @property
    def ratio(self) -> float | None:
        if self.baseline is None or self.baseline == 0:
            return None
        return self.ours / self.baseline


def median_of(runs: int, fn: Callable[[], float]) -> float:
    return statistics.median(fn() for _ in range(runs))


def machine() -> str:
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"python-can {can.__version__}, {platform.system()} {platform.release()}"
    )


def fmt(value: float | None, unit: str = "") -> str:
    if value is None:
        return "–"
    text = f"{value:,.3g}" if abs(value) < 1000 else f"{value:,.0f}"
    return f"{text} {unit}".strip()


def print_rows(rows: list[Row], out: Callable[[str], None] = print) -> None:
    header = f"{'figure':<54} {'ours':>14} {'baseline':>14} {'ratio':>7}  target"
    section = ""
    for row in rows:
        if row.section != section:
            section = row.section
            out("")
            out(f"## {section}")
            out(header)
        verdict = {True: "  ok", False: "  MISSED", None: ""}[row.ok]
        ratio = f"{row.ratio:.2f}x" if row.ratio is not None else "–"
        out(
            f"{row.figure:<54} {fmt(row.ours, row.unit):>14} {fmt(row.baseline, row.unit):>14} "
            f"{ratio:>7}  {row.target}{verdict}"
        )
    sys.stdout.flush()
