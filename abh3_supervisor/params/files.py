"""Parameter sets on disk: the maker's CSV, YAML and JSON (format by extension).

The maker's PC tool imports/exports CSV in cp932 with the columns decimal address, name,
display value, internal value (§1.4). Whether it has a header row, and how it writes the
internal value, no public source shows: we write no header and the internal value as a
signed decimal 32-bit integer, and read rows whose first cell is not a number as headers,
and internal values in decimal or ``0x`` hex. The internal value wins over the display
value when both are given (it is what the drive holds, bit for bit).
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import yaml

from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.params import table
from abh3_supervisor.params.telabh3 import signed

ENCODING = "cp932"  # the maker's tool (Shift-JIS with Microsoft's extensions)


class ParamFileError(Abh3Error):
    """A parameter file cannot be read: which file, which row, what is wrong."""


@dataclass(frozen=True, slots=True)
class ParamValue:
    address: int
    word: int  # the 32-bit word the drive holds

    @property
    def name(self) -> str:
        return table.label(self.address)

    @property
    def value(self) -> float:
        return table.to_value(self.word, table.kind_of(self.address))

    @property
    def shown(self) -> str:
        return table.display(self.value)


def dumps(values: Iterable[ParamValue], fmt: str, unit: str = "") -> str:
    """``fmt``: ``csv``, ``yaml`` or ``json``."""
    values = list(values)
    if fmt == "csv":
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\r\n")  # the maker's tool is a Windows one
        for v in values:
            writer.writerow([v.address, v.name, v.shown, signed(v.word, 32)])
        return out.getvalue()
    doc = {
        "unit": unit,
        "parameters": [
            {
                "address": f"0x{v.address:04X}",
                "name": v.name,
                "value": v.shown,
                "word": f"0x{v.word:08X}",
            }
            for v in values
        ],
    }
    if fmt == "json":
        return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)


def format_of(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix == ".json":
        return "json"
    if suffix in (".yaml", ".yml"):
        return "yaml"
    raise ParamFileError(f"{path}: use .csv (the maker's format), .yaml or .json")


def write(path: Path, values: Iterable[ParamValue], unit: str = "") -> None:
    fmt = format_of(path)
    text = dumps(values, fmt, unit)
    try:
        path.write_bytes(text.encode(ENCODING if fmt == "csv" else "utf-8"))
    except OSError as exc:
        raise ParamFileError(f"{path}: cannot write: {exc.strerror}") from exc


def read(path: Path) -> list[ParamValue]:
    fmt = format_of(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ParamFileError(f"{path}: cannot read: {exc.strerror}") from exc
    if fmt == "csv":
        try:
            rows: list[list[object]] = [
                list(r) for r in csv.reader(io.StringIO(raw.decode(ENCODING)))
            ]
        except UnicodeDecodeError as exc:
            raise ParamFileError(f"{path}: not cp932 text: {exc}") from None
        return _rows(path, rows, header=True)
    try:
        doc = json.loads(raw) if fmt == "json" else yaml.safe_load(raw)
    except (ValueError, yaml.YAMLError) as exc:
        raise ParamFileError(f"{path}: {exc}") from None
    items = doc.get("parameters") if isinstance(doc, dict) else None
    if not isinstance(items, list):
        raise ParamFileError(f"{path}: expected a 'parameters:' list (as `abh3 param dump` writes)")
    rows = []
    for item in items:
        if not isinstance(item, dict):
            raise ParamFileError(f"{path}: each parameter is a mapping, not {item!r}")
        rows.append([item.get("address"), item.get("name"), item.get("value"), item.get("word")])
    return _rows(path, rows, header=False)


def _rows(path: Path, rows: Iterable[list[object]], header: bool) -> list[ParamValue]:
    """``header``: the first row may be a header (the maker's CSV); YAML/JSON have none."""
    values: list[ParamValue] = []
    for n, row in enumerate(rows, 1):
        if not row or all(c in (None, "") for c in row):
            continue
        address_text = str(row[0]).strip()
        try:
            address = table.parse_address(address_text)
        except Abh3Error:
            if header and n == 1:
                continue  # a header row
            raise ParamFileError(f"{path}:{n}: '{address_text}' is no address") from None
        internal = row[3] if len(row) > 3 else None
        shown = row[2] if len(row) > 2 else None
        try:
            if internal not in (None, ""):
                word = int(str(internal), 0) & 0xFFFFFFFF
            elif shown not in (None, ""):
                word = table.to_word(float(str(shown)), table.kind_of(address))
            else:
                raise ValueError("no value")
        except (ValueError, Abh3Error) as exc:
            raise ParamFileError(f"{path}:{n}: 0x{address:04X}: {exc}") from None
        values.append(ParamValue(address, word))
    return values
