"""Parameter sets on disk: the maker's CSV, YAML and JSON (format by extension).

The maker's PC tool imports/exports CSV in cp932 with the columns decimal address, name,
display value, internal value (§1.4). Its public AGV file (wacogiken/ABH3_AI,
``ABH3_Paramater_AGV_AI.csv``) starts with the header row
``パラメータアドレス,パラメータ名,パラメータ値(表示値),パラメータ値(内部値)``, writes the
internal value as a decimal integer (signed: ``-1``) and the display value as the tool
shows it — often with a unit (``800 [min^-1]``), in another unit than the word
(``250[kbps]`` for 250000) or as a word (``CANホスト``). We write no header (as before)
and the internal value as a signed decimal.

Reading, nothing is sent that the file did not mean: the whole file is checked before
anything is returned, and every mistake is a :class:`ParamFileError` naming ``file:row``
(the CSV's line; YAML/JSON: the entry's place in ``parameters``), the address and the
value — docs/parameters.md, "Files", lists the rules. Files are bounded (size, rows, and
nesting for YAML/JSON) before they are parsed.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml

from abh3_supervisor.errors import Abh3Error, CodecError
from abh3_supervisor.params import table
from abh3_supervisor.params.table import quote
from abh3_supervisor.params.telabh3 import signed, unpack_float

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


MAX_BYTES = 1 << 20  # 1 MiB: a full parameter set is a few kB (the maker's AGV file 12 kB)
MAX_ROWS = 8 * len(table.PARAMETERS)  # 968: the maker's file holds 247 addresses; ours 121
MAX_DEPTH = 8  # YAML/JSON: ours needs 3 (the document, its parameter list, an entry)
MAX_NODES = 10 * MAX_ROWS  # YAML/JSON values of every kind: an entry has 5 at most (+ keys)

# The only first rows taken as a header (cells compared stripped; English ignoring case):
# the maker's, as in its public file, and ours in English (long and short column names).
MAKER_HEADER = (
    "パラメータアドレス",
    "パラメータ名",
    "パラメータ値(表示値)",
    "パラメータ値(内部値)",
)
HEADERS = (
    MAKER_HEADER,
    ("address", "name", "display value", "internal value"),
    ("address", "name", "display", "internal"),
)
KEYS = ("address", "name", "value", "word")  # a YAML/JSON entry's keys, in CSV column order
Cell = str | int | float | None


def read(path: Path, *, allow_unknown: bool = True) -> list[ParamValue]:
    """Every row of the file, checked (see the module docstring), or ParamFileError.

    ``allow_unknown``: addresses not in the parameter table are read too (the TUI's
    comparison shows them as not read); ``abh3 param diff/restore`` refuse them unless
    ``--allow-unknown`` is given."""
    fmt = format_of(path)
    raw = _bounded(path)
    try:
        if fmt == "csv":
            return _check(path, _csv_rows(path, raw), allow_unknown)
        return _check(path, _doc_rows(path, raw, fmt), allow_unknown)
    except RecursionError:  # the pre-scan bounds nesting: this is the last line of defence
        raise ParamFileError(f"{path}: nested too deeply (more than {MAX_DEPTH} levels)") from None


def _bounded(path: Path) -> bytes:
    """The file's bytes, refused beyond MAX_BYTES without reading more than that."""
    try:
        with path.open("rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise ParamFileError(f"{path}: cannot read: {exc.strerror}") from exc
    if len(raw) > MAX_BYTES:
        raise ParamFileError(
            f"{path}: larger than {MAX_BYTES >> 20} MiB: not a parameter set "
            "(a full one is a few kB)"
        )
    return raw


def _csv_rows(path: Path, raw: bytes) -> Iterator[tuple[int, list[Cell]]]:
    """(line, cells) of each row that is not blank; the first may be a header."""
    try:
        text = raw.decode(ENCODING)
    except UnicodeDecodeError as exc:
        raise ParamFileError(f"{path}: not cp932 text: {exc}") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    first = True
    try:
        for cells in reader:
            if not any(c.strip() for c in cells):
                continue
            if first and _is_header(cells):
                first = False
                continue
            first = False
            while cells and not cells[-1].strip():  # trailing empty cells (a spreadsheet's)
                cells.pop()
            if len(cells) > len(KEYS):
                raise ParamFileError(
                    f"{path}:{reader.line_num}: {len(cells)} cells: expected address, name, "
                    "display value, internal value (is a name with a comma not quoted?)"
                )
            yield reader.line_num, list(cells)
    except csv.Error as exc:
        raise ParamFileError(f"{path}:{reader.line_num}: not CSV: {exc}") from None


def _is_header(cells: list[str]) -> bool:
    key = tuple(c.strip() for c in cells)
    return key == MAKER_HEADER or tuple(c.lower() for c in key) in HEADERS[1:]


def _doc_rows(path: Path, raw: bytes, fmt: str) -> Iterator[tuple[int, list[Cell]]]:
    """(entry number, cells) of a YAML/JSON ``parameters`` list, after the pre-scan."""
    try:
        if fmt == "json":
            try:
                text = raw.decode("utf-8-sig")
            except UnicodeDecodeError as exc:
                raise ParamFileError(f"{path}: not UTF-8 text: {exc}") from None
            _scan_json(path, text)
            doc = json.loads(text)
        else:
            _scan_yaml(path, raw)
            doc = yaml.safe_load(raw)
    except (ValueError, yaml.YAMLError) as exc:
        raise ParamFileError(f"{path}: {exc}") from None
    items = doc.get("parameters") if isinstance(doc, dict) else None
    if not isinstance(items, list):
        raise ParamFileError(f"{path}: expected a 'parameters:' list (as `abh3 param dump` writes)")
    for n, item in enumerate(items, 1):
        if not isinstance(item, dict):
            raise ParamFileError(f"{path}:{n}: each parameter is a mapping, not {_short(item)}")
        extra = [str(k) for k in item if k not in KEYS]
        if extra:
            raise ParamFileError(
                f"{path}:{n}: unknown key(s) {', '.join(map(repr, extra))}: an entry has "
                "address, name, value, word"
            )
        cells: list[Cell] = []
        for key in KEYS:
            cell = item.get(key)
            if isinstance(cell, bool) or not isinstance(cell, str | int | float | None):
                raise ParamFileError(
                    f"{path}:{n}: {key} is a {type(cell).__name__}: write a number or a string"
                )
            cells.append(cell)
        yield n, cells


def _short(value: object) -> str:
    """A value in a message, never the whole of a huge or self-referencing one."""
    return type(value).__name__ if isinstance(value, list | dict) else repr(value)[:40]


def _scan_yaml(path: Path, raw: bytes) -> None:
    """Nesting and size from the parser's events (an iterative state machine, unlike the
    recursive composer that builds the document): refused before the document is built."""
    depth = nodes = 0
    for event in yaml.parse(raw, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                raise ParamFileError(_too_deep(path))
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1
        if isinstance(event, yaml.NodeEvent):
            nodes += 1
            if nodes > MAX_NODES:
                raise ParamFileError(_too_many(path))


def _scan_json(path: Path, text: str) -> None:
    """Nesting, counted over the brackets outside strings, before ``json.loads``."""
    depth = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > MAX_DEPTH:
                raise ParamFileError(_too_deep(path))
        elif ch in "]}":
            depth -= 1


def _too_deep(path: Path) -> str:
    return f"{path}: nested more than {MAX_DEPTH} levels deep: not a parameter set"


def _too_many(path: Path) -> str:
    known = len(table.PARAMETERS)
    return f"{path}: more than {MAX_ROWS} parameters: not a parameter set (the table has {known})"


def _check(
    path: Path, rows: Iterable[tuple[int, list[Cell]]], allow_unknown: bool
) -> list[ParamValue]:
    """Every row checked; the first mistake ends the read, before anything is written."""
    values: list[ParamValue] = []
    seen: dict[int, int] = {}  # address → its row
    for n, cells in rows:
        if len(values) == MAX_ROWS:
            raise ParamFileError(_too_many(path))
        where = f"{path}:{n}"
        value = _value(where, cells, allow_unknown)
        if value.address in seen:
            raise ParamFileError(
                f"{where}: 0x{value.address:04X} {value.name} is also on row "
                f"{seen[value.address]}: one value per address"
            )
        seen[value.address] = n
        values.append(value)
    return values


def _float(text: str) -> float:
    """``float(text)``, 0.0 for what is no float at all."""
    try:
        return float(text)
    except ValueError:
        return 0.0


def _text(cell: Cell) -> str:
    return "" if cell is None else str(cell).strip()


def _value(where: str, cells: list[Cell], allow_unknown: bool) -> ParamValue:
    address_text, name, shown, internal = (_text(c) for c in [*cells, *[None] * 4][:4])
    try:
        address = table.parse_address(address_text)
    except CodecError:
        raise ParamFileError(f"{where}: {quote(address_text)} is no address") from None
    entry = table.BY_ADDRESS.get(address)
    what = f"{where}: 0x{address:04X} {table.label(address)}"
    if entry is None and not allow_unknown:
        raise ParamFileError(
            f"{what}: not in the parameter table (a typo? --allow-unknown reads it anyway)"
        )
    named = table.BY_NAME.get(name.upper())
    if named is not None and named.address != address:
        raise ParamFileError(f"{what}: named {named.name}, which is 0x{named.address:04X}")
    kinds: tuple[table.Kind, ...] = (entry.kind,) if entry is not None else ("pf", "int")
    number = table.parse_number(shown) if shown else None
    if shown and not math.isfinite(_float(shown)):  # also "nan", "inf", "-Infinity"
        raise ParamFileError(
            f"{what}: display value {quote(shown)} is not finite: NaN and infinities are refused"
        )
    if internal:
        try:
            word = table.parse_word(internal)
        except CodecError as exc:
            raise ParamFileError(f"{what}: internal value {exc}") from None
        if entry is not None and entry.kind == "pf" and not math.isfinite(unpack_float(word)):
            meaning = table.display(unpack_float(word))
            raise ParamFileError(
                f"{what}: internal value {quote(internal)} is {meaning} as a packed float: refused"
            )
        if number is not None and not any(_agree(number, word, k) for k in kinds):
            means = table.display(table.to_value(word, kinds[0]))
            raise ParamFileError(
                f"{what}: display value {quote(shown)} and internal value {quote(internal)} "
                f"(= {means}) disagree: correct one, or leave the display value empty"
            )
        return ParamValue(address, word)
    if not shown:
        raise ParamFileError(f"{what}: no value (display or internal)")
    if number is None:
        raise ParamFileError(f"{what}: display value {quote(shown)} is not a number")
    try:
        return ParamValue(address, table.to_word(number, kinds[0]))
    except CodecError as exc:
        raise ParamFileError(f"{what}: display value {quote(shown)}: {exc}") from None


def _agree(number: float, word: int, kind: table.Kind) -> bool:
    """Whether a display value means ``word`` read as ``kind`` (a decimal display and a
    packed float are exact decimals: equal up to the last bit of a double)."""
    if kind == "int":
        return (
            number == int(number)
            and table.INT_MIN <= number <= table.WORD_MAX
            and (int(number) & table.WORD_MAX == word)
        )
    return math.isclose(table.to_value(word, kind), number, rel_tol=1e-9)
