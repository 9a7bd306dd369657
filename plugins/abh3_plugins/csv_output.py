"""``csv``: record each unit's feedback and status in physical units.

One row per DP0 reply (or at most one per ``period_s``) with the setpoint in force (as
sent: rounded to the frame's resolution), the feedback in both velocity models and the
latest status packets, each at its frame's resolution, units in the header; flag words as
hex plus their bit names: the input word commanded, and the control, I/O (and in 2023
input) words the drive reports. After the drives were stopped, one last row per unit
(note ``after the stop``) holds the state the stop left: the safe word commanded, the
reply to it, the control word as last reported (2021: broadcast 1, which the stop does
not wait for). ``path`` with ``{unit}`` in it gives one file per unit, else one file with
a ``unit`` column. Rows are flushed every ``flush_s`` (0.5 s; at most 1 s) on a fixed
grid and on every way out, so a ``kill -9`` loses at most the rows of the last
``flush_s``, and the file ends in a whole row; files rotate by size (``rotate_bytes``) or
age (``rotate_s``). All writing happens off the bus path: rows on this plugin's worker
thread, flushes on a thread of their own.
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

from abh3_supervisor.plugin_api import (
    CURRENT,
    VELOCITY,
    ControlMode,
    Feedback,
    Section,
    Setpoint,
    SupervisorView,
    UnitView,
    flags,
    frames,
    hookimpl,
)
from abh3_supervisor.plugin_api import schema as js

# flag-word columns; each unit's bits are named in its generation's layout. ``inputs`` is
# the word the host commands; ``drive_inputs`` the one the drive reports (2023 broadcast 1)
FLAG_WORDS = ("error", "alarm", "control", "io", "inputs", "drive_inputs")
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
    "note",
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
# (unit, decimals) of each number: the resolution its frame carries it in
FORMATS: dict[str, tuple[str, int | None]] = {
    "time": ("s", 6),
    "cmd_ay": ("min-1 or %", None),  # by the setpoint's kind
    "cmd_bx": ("min-1 or %", None),
    **{c: ("min-1", 1) for c in ("vel_a", "vel_b", "vel_y", "vel_x", "vel_cmd_ay", "vel_cmd_bx")},
    "cur_cmd_ay": ("%", 2),
    "cur_cmd_bx": ("%", 2),
    "load_a": ("%", 0),
    "load_b": ("%", 0),
    "analog0": ("V", 2),
    "analog1": ("V", 2),
    "main_volt": ("V", 1),
    "control_volt": ("V", 1),
}
HEADER = {c: f"{c} [{FORMATS[c][0]}]" if c in FORMATS else c for c in COLUMNS}
FLUSH_S = 0.5  # default seconds between flushes: at most what a kill -9 loses
MONITOR_DIGITS = 7  # monitors are float32: seven significant digits hold all they carry


ABH3_API_VERSION = "1.3"  # the plugin API this is written for (abh3_feedback's inputs)


def number(column: str, value: float) -> str:
    decimals = FORMATS.get(column, ("", None))[1]
    if decimals is None:
        return f"{value:.{MONITOR_DIGITS}g}"
    return f"{value + 0.0:.{decimals}f}"  # + 0.0: never "-0.0"


def command(setpoint: Setpoint, value: float) -> str:
    """The command as the frame carried it (the LSB of its kind)."""
    scale = CURRENT if setpoint.kind is ControlMode.CURRENT else VELOCITY
    return f"{scale.to_physical(scale.to_raw(value)[0]) + 0.0:.{2 if scale is CURRENT else 1}f}"


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
        self.writer: Any = csv.DictWriter(self.pending, COLUMNS)  # header: with units
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
        self.writer.writerow(HEADER)
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
        self.flush_s = FLUSH_S
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
        self.units: dict[str, UnitView] = {}

    @hookimpl
    def abh3_config_schema(self) -> dict[str, Any]:
        return js.mapping(
            {
                "path": js.text("file; {unit} in it gives one file per unit", "abh3.csv"),
                "period_s": js.number(0.0, 3600.0, "0: a row per DP0 reply", 0.0),
                "flush_s": js.number(
                    0.0,
                    1.0,
                    "seconds between flushes: what a kill -9 may lose",
                    FLUSH_S,
                    lo_open=True,
                ),
                "rotate_bytes": js.integer(0, 2**40, "0: off", 0),
                "rotate_s": js.number(0.0, 30 * 86400.0, "0: off", 0.0),
            }
        )

    @hookimpl
    def abh3_configure(self, section: Section) -> None:
        section.only({"path", "period_s", "flush_s", "rotate_bytes", "rotate_s"})
        self.path = Path(section.output_path("path", str(self.path)))
        self.period_s = section.number("period_s", 0.0, 0.0, 3600.0)
        self.flush_s = section.number("flush_s", FLUSH_S, 0.0, 1.0, lo_open=True)
        self.rotate_bytes = section.integer("rotate_bytes", 0, 0, 2**40)
        self.rotate_s = section.number("rotate_s", 0.0, 0.0, 30 * 86400.0)

    @hookimpl
    def abh3_start(self, supervisor: SupervisorView) -> None:
        self.units = dict(supervisor.units)
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
        due = time.monotonic()
        while True:  # on a grid: the time a flush takes never stretches the interval
            due = max(due + self.flush_s, time.monotonic())
            if self._stop.wait(due - time.monotonic()):
                return
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
            if key == "inputs" and value is not None:  # 2023 broadcast 1: as the drive sees
                values["drive_inputs"] = f"0x{value:08X}"
                values["drive_inputs_names"] = " ".join(words[key].names(value))
            elif key in FLAG_WORDS and value is not None:
                values[key] = f"0x{value:08X}"
                values[f"{key}_names"] = " ".join(words[key].names(value))
            elif key in STATUS_FIELDS:
                values[key] = number(key, value)

    @hookimpl
    def abh3_feedback(self, unit: str, feedback: Feedback, setpoint: Setpoint, inputs: int) -> None:
        self._check()
        if self.period_s and feedback.t - self.last_row.get(unit, -1e18) < self.period_s:
            return
        self.last_row[unit] = feedback.t
        row = self._row(unit, feedback, setpoint, inputs, feedback.control)
        with self.lock:
            self._file(unit).write(row)

    def _row(
        self, unit: str, feedback: Feedback, setpoint: Setpoint, inputs: int, control: int | None
    ) -> dict[str, Any]:
        wall = time.time() - (time.monotonic() - feedback.t)  # event time on the wall clock
        layout = self.layouts[unit]
        row = {
            "time": number("time", wall),
            "unit": unit,
            "kind": setpoint.kind.value,
            "cmd_ay": command(setpoint, setpoint.ay),
            "cmd_bx": command(setpoint, setpoint.bx),
            **{c: number(c, getattr(feedback, c)) for c in ("vel_a", "vel_b", "vel_y", "vel_x")},
            **self.latest.get(unit, {}),
            "inputs": f"0x{inputs:08X}",
            "inputs_names": " ".join(layout.input.names(inputs)),
        }
        if control is not None:
            row["control"] = f"0x{control:08X}"
            row["control_names"] = " ".join(layout.control.names(control))
        return row

    @hookimpl
    def abh3_stop(self) -> None:
        self._stop.set()
        if self._flusher is not None:
            self._flusher.join(2)
        with self.lock:
            try:
                if self.failure is None:
                    self._final_rows()
            finally:
                for f in self.files.values():
                    f.close(flush=self.failure is None)  # after a failure: whole rows stay

    def _final_rows(self) -> None:
        """The drives were stopped and every reply handed over: the state the stop left,
        as the drive last reported it, one row per unit that ever answered."""
        for name, unit in self.units.items():
            if unit.feedback is None:
                continue
            row = self._row(
                name, unit.feedback, unit.setpoint, unit.inputs, unit.words.get("control")
            )
            row["note"] = "after the stop"
            self._file(name).write(row)
