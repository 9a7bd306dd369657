"""``csv``: record each unit's feedback and status in physical units.

One row per DP0 reply (or at most one per ``period_s``) with the setpoint in force, the
feedback in both velocity models and the latest status packets; flag words as hex plus
their bit names. ``path`` with ``{unit}`` in it gives one file per unit, else one file
with a ``unit`` column. Rows are flushed at least every ``flush_s`` (≤ 1 s) and on every
way out; files rotate by size (``rotate_bytes``) or age (``rotate_s``). All writing
happens on this plugin's worker thread, never on the bus path.
"""

from __future__ import annotations

import contextlib
import csv
import io
import os
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import IO, Any

from abh3_supervisor.config.source import Section
from abh3_supervisor.hookspecs import hookimpl
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.state import Feedback, Setpoint
from abh3_supervisor.supervisor import Supervisor

# flag-word columns; each unit's bits are named in its generation's layout
FLAG_WORDS = ("error", "alarm", "control", "io", "inputs")
STATUS_FIELDS = [
    "vel_cmd_ay",
    "vel_cmd_bx",
    "cur_cmd_ay",
    "cur_cmd_bx",
    "load_a",
    "load_b",
    "pulse_a",
    "pulse_b",
    "analog0",
    "analog1",
    "main_volt",
    "control_volt",
    "monitor0",
    "monitor1",
]
COLUMNS = [
    "time",
    "unit",
    "kind",
    "cmd_ay",
    "cmd_bx",
    "vel_a",
    "vel_b",
    "vel_y",
    "vel_x",
    *STATUS_FIELDS,
    *[c for w in FLAG_WORDS for c in (w, f"{w}_names")],
]


class _File:
    """One CSV file (and its rotations), written whole rows at a time: rows gather in
    memory and go out at each flush; a write that fails (disk full) is cut back to the
    last whole row, so the file never ends in a partial row."""

    def __init__(self, path: Path, rotate_bytes: int, rotate_s: float) -> None:
        self.base, self.rotate_bytes, self.rotate_s = path, rotate_bytes, rotate_s
        self.index = 0
        self.handle: IO[bytes] | None = None
        self.size = 0  # bytes of whole rows on disk
        self.pending = io.StringIO()
        self.writer: Any = csv.DictWriter(self.pending, COLUMNS)
        self.opened = 0.0
        self._open()

    @property
    def name(self) -> Path:
        if not (self.rotate_bytes or self.rotate_s):
            return self.base
        return self.base.with_name(f"{self.base.stem}-{self.index:04d}{self.base.suffix}")

    def _open(self) -> None:
        self.base.parent.mkdir(parents=True, exist_ok=True)
        self.handle = open(self.name, "wb", buffering=0)  # noqa: SIM115
        self.size = 0
        self.opened = time.monotonic()
        self.writer.writeheader()
        self.flush()

    def write(self, row: dict[str, Any]) -> None:
        assert self.handle is not None
        if (self.rotate_bytes and self.size + self.pending.tell() >= self.rotate_bytes) or (
            self.rotate_s and time.monotonic() - self.opened >= self.rotate_s
        ):
            self.flush()
            self.handle.close()
            self.index += 1
            self._open()
        self.writer.writerow(row)

    def flush(self) -> None:
        if self.handle is None:
            return
        data = self.pending.getvalue().encode("utf-8")
        self.pending.seek(0)
        self.pending.truncate()
        if not data:
            return
        try:
            written = 0
            while written < len(data):
                written += self.handle.write(data[written:]) or 0
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(self.handle.fileno(), self.size)  # back to the last whole row
                self.handle.seek(self.size)
            raise OSError(exc.errno, exc.strerror, str(self.name)) from exc
        self.size += len(data)

    def close(self, flush: bool = True) -> None:
        if self.handle is not None:
            try:
                if flush:
                    self.flush()
            finally:
                self.handle.close()
                self.handle = None


class CsvPlugin:
    def __init__(self) -> None:
        self.path = Path("abh3.csv")
        self.period_s = 0.0
        self.flush_s = 1.0
        self.rotate_bytes = 0
        self.rotate_s = 0.0
        self.files: dict[str, _File] = {}
        self.latest: dict[str, dict[str, Any]] = {}  # unit → latest status values
        self.last_row: dict[str, float] = {}
        self.layouts: dict[str, flags.Layout] = {}
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._flusher: threading.Thread | None = None
        self.failure: OSError | None = None  # the output failed: raised to the host

    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        section.only({"path", "period_s", "flush_s", "rotate_bytes", "rotate_s"})
        self.path = Path(section.output_path("path", str(self.path)))
        self.period_s = section.number("period_s", 0.0, 0.0, 3600.0)
        self.flush_s = section.number("flush_s", 1.0, 0.0, 1.0, lo_open=True)
        self.rotate_bytes = section.integer("rotate_bytes", 0, 0, 2**40)
        self.rotate_s = section.number("rotate_s", 0.0, 0.0, 30 * 86400.0)

    @hookimpl
    def abh3_start(self, supervisor: Supervisor) -> None:
        self.layouts = {name: unit.layout for name, unit in supervisor.units.items()}
        names = supervisor.units if "{unit}" in str(self.path) else ["*"]
        for name in names:
            path = Path(str(self.path).replace("{unit}", name))
            self.files[name] = _File(path, self.rotate_bytes, self.rotate_s)
        self._flusher = threading.Thread(target=self._flush_loop, name="csv flush", daemon=True)
        self._flusher.start()

    def _file(self, unit: str) -> _File:
        return self.files.get(unit) or self.files["*"]

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_s):
            try:
                with self.lock:
                    for f in self.files.values():
                        f.flush()
            except OSError as exc:  # the host hears of it with the next event
                self.failure = exc
                return

    def _check(self) -> None:
        if self.failure is not None:
            raise self.failure

    @hookimpl
    def abh3_status(self, unit: str, record: frames.Broadcast) -> None:
        self._check()
        values = self.latest.setdefault(unit, {})
        words = self.layouts[unit].words
        for key, value in asdict(record).items():
            if key in FLAG_WORDS and value is not None:
                values[key] = f"0x{value:08X}"
                values[f"{key}_names"] = " ".join(words[key].names(value))
            elif key in STATUS_FIELDS:
                values[key] = value

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback, setpoint: Setpoint) -> None:
        self._check()
        if self.period_s and feedback.t - self.last_row.get(unit, -1e18) < self.period_s:
            return
        self.last_row[unit] = feedback.t
        wall = time.time() - (time.monotonic() - feedback.t)  # event time on the wall clock
        row = {
            "time": f"{wall:.6f}",
            "unit": unit,
            "kind": setpoint.kind.value,
            "cmd_ay": setpoint.ay,
            "cmd_bx": setpoint.bx,
            "vel_a": feedback.vel_a,
            "vel_b": feedback.vel_b,
            "vel_y": feedback.vel_y,
            "vel_x": feedback.vel_x,
            **self.latest.get(unit, {}),
        }
        if feedback.control is not None:
            row["control"] = f"0x{feedback.control:08X}"
            control = self.layouts[unit].control
            row["control_names"] = " ".join(control.names(feedback.control))
        with self.lock:
            self._file(unit).write(row)

    @hookimpl
    def abh3_stop(self) -> None:
        self._stop.set()
        if self._flusher is not None:
            self._flusher.join(2)
        with self.lock:
            for f in self.files.values():
                f.close(flush=self.failure is None)  # after a failure: what is whole stays
