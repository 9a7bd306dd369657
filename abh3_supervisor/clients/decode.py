"""``abh3 decode``: an ABH3-aware reading of a recording made by ``--record``."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from typing import Any

import can

from abh3_supervisor.clients.scan import Findings
from abh3_supervisor.config.model import Config, VelocityModel
from abh3_supervisor.core import readouts
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.classify import AddressBook, DecodedFrame, Kind, classify


def address_books(config: Config | None) -> dict[str, AddressBook]:
    """One book per bus channel (addresses repeat across buses) — also under the bus's
    name, which an MCAP recording's topics carry — and under ``""`` one for frames that
    name no known channel: there an id counts only where all buses agree."""
    if config is None:
        return {"": AddressBook()}
    books: dict[str, AddressBook] = {}
    for bus in config.buses.values():
        units = config.units_on(bus.name)
        books[bus.channel] = AddressBook(
            hosts=frozenset(u.host_id for u in units) or frozenset({2}),
            generations={u.abh3_id: u.protocol for u in units},
        )
    for bus in config.buses.values():  # a real channel wins over a bus of that name
        books.setdefault(bus.name, books[bus.channel])
    every = list(config.units.values())
    generations = {u.abh3_id: u.protocol for u in every}
    agreed = {
        a: g
        for a, g in generations.items()
        if all(u.protocol is g for u in every if u.abh3_id == a)
    }
    books[""] = AddressBook(hosts=frozenset(u.host_id for u in every), generations=agreed)
    return books


def unit_names(config: Config | None) -> dict[tuple[str, int], str]:
    """(channel or bus name, abh3_id) → unit name; channel '' matches any when the id is
    unique."""
    if config is None:
        return {}
    names: dict[tuple[str, int], str] = {}
    for u in config.units.values():
        names[(config.buses[u.bus].channel, u.abh3_id)] = u.name
        names[("", u.abh3_id)] = u.name if ("", u.abh3_id) not in names else "?"
    for u in config.units.values():
        names.setdefault((u.bus, u.abh3_id), u.name)
    return names


Models = dict[tuple[str, int], VelocityModel]


def velocity_models(config: Config | None) -> Models:
    """(channel or bus name, abh3_id) → the unit's velocity model: what its AY/BX fields
    are. Channel '' holds an id whose units all agree."""
    if config is None:
        return {}
    models: Models = {}
    every = list(config.units.values())
    for u in every:
        models[(config.buses[u.bus].channel, u.abh3_id)] = u.velocity_model
    for u in every:  # a real channel wins over a bus of that name
        models.setdefault((u.bus, u.abh3_id), u.velocity_model)
        if all(o.velocity_model is u.velocity_model for o in every if o.abh3_id == u.abh3_id):
            models[("", u.abh3_id)] = u.velocity_model
    return models


def read_messages(path: Path, report: Callable[[str], None] | None = None) -> Iterator[can.Message]:
    """The frames of a recording, reading past what cannot be read.

    In the text formats (.log, .asc, .csv) a line that cannot be read is reported with its
    number and skipped; a binary file (.blf) is read up to where it breaks off. Then the
    count of what was skipped. Reports go to ``report`` (stderr by default), at most SHOWN
    one by one. Raises Abh3Error when the file cannot be opened, or when it has content
    and not one frame could be read from it (it is not a recording of that format; .asc
    readers pass over lines they do not know without a word).
    """
    say = report or _to_stderr
    kind = _TEXT_READERS.get(path.suffix.lower())
    try:
        if path.suffix.lower() == ".mcap":
            from abh3_supervisor.runtime.mcap_recording import read_frames

            read, unread = yield from read_frames(path, say)
        elif kind is not None:
            read, unread = yield from _text_frames(path, kind, say)
        else:
            read, unread = yield from _binary_frames(path, say)
    except OSError as exc:
        raise Abh3Error(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    except ValueError as exc:  # python-can has no reader for this extension
        raise Abh3Error(f"{path}: cannot read recording: {exc}") from exc
    if unread and not read:
        raise Abh3Error(f"{path}: no frame could be read: is it a {path.suffix} recording?")


SHOWN = 20  # unreadable lines reported one by one; the rest are only counted
_TEXT_READERS: dict[str, type[can.io.generic.TextIOMessageReader]] = {
    ".log": can.CanutilsLogReader,
    ".asc": can.ASCReader,
    ".csv": can.CSVReader,
}
# what a reader started in the middle of a file consumes before its first frame line
_PREAMBLE = {can.ASCReader: "\n", can.CSVReader: "header\n"}


def _to_stderr(text: str) -> None:
    print(text, file=sys.stderr)


class _Lines:
    """A file's lines for python-can's readers, numbered; a line can be put in front."""

    def __init__(self, lines: Iterator[str]) -> None:
        self._lines = lines
        self._front: list[str] = []
        self.number = 0
        self.last = ""
        self.content = False  # a line that is not blank was seen

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        if self._front:
            return self._front.pop()
        self.last = next(self._lines)
        self.number += 1
        self.content = self.content or not self.last.isspace()
        return self.last

    def put_front(self, line: str) -> None:
        self._front.append(line)

    def close(self) -> None:
        """Readers close their file when done; this one is closed by its owner."""


def _text_frames(
    path: Path, kind: type[can.io.generic.TextIOMessageReader], say: Callable[[str], None]
) -> Generator[can.Message, None, tuple[int, int]]:
    read = skipped = 0
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = _Lines(f)
        reader = kind(lines)  # type: ignore[arg-type]
        while True:
            try:
                for msg in reader:
                    read += 1
                    yield msg
                break
            except Exception as exc:  # python-can's parsers fail on garbage in many ways
                skipped += 1
                if skipped <= SHOWN:
                    say(
                        f"{path}:{lines.number}: cannot read {lines.last.strip()[:60]!r} "
                        f"({exc or type(exc).__name__}), skipped"
                    )
                reader = _resumed(kind, reader, lines)
    if skipped:
        say(f"{path}: {skipped} unreadable line(s) skipped, {read} frame(s) read")
    return read, skipped or int(lines.content)  # unread: something, if there was text


def _resumed(
    kind: type[can.io.generic.TextIOMessageReader],
    old: can.io.generic.TextIOMessageReader,
    lines: _Lines,
) -> can.io.generic.TextIOMessageReader:
    """A reader that goes on after the bad line, with what the old one knew (ASC base)."""
    preamble = _PREAMBLE.get(kind)
    if preamble is not None:
        lines.put_front(preamble)
    reader = kind(lines)  # type: ignore[arg-type]
    reader.__dict__.update({k: v for k, v in vars(old).items() if k != "file"})
    return reader


def _binary_frames(
    path: Path, say: Callable[[str], None]
) -> Generator[can.Message, None, tuple[int, int]]:
    """.blf and whatever else python-can reads: up to where the file breaks off."""
    read = 0
    try:
        reader = can.LogReader(str(path))
    except (OSError, ValueError):
        raise  # cannot open it, or no reader for the extension: the caller says so
    except Exception as exc:  # not this format at all (a BLF without its header)
        say(f"{path}: not a {path.suffix} recording ({exc or type(exc).__name__})")
        return 0, 1
    try:
        for msg in reader:
            read += 1
            yield msg
    except Exception as exc:  # truncated or damaged: struct, zlib and parser errors
        say(f"{path}: cannot read past frame {read} ({exc or type(exc).__name__}), rest skipped")
        return read, 1
    finally:
        reader.stop()
    return read, 0


def record(
    msg: can.Message,
    books: dict[str, AddressBook],
    names: dict[tuple[str, int], str],
    models: Models | None = None,
) -> dict[str, Any]:
    book = books.get(str(msg.channel or "")) or books[""]
    frame = classify(msg.arbitration_id, bytes(msg.data), msg.is_extended_id, book)
    if msg.is_remote_frame or msg.is_error_frame:  # an ABH3 sends neither: no payload
        what = "remote frame" if msg.is_remote_frame else "error frame"
        frame = DecodedFrame(Kind.UNKNOWN, frames.Unknown(what), frame.priority)
    out: dict[str, Any] = {
        "t": msg.timestamp if math.isfinite(msg.timestamp) else None,  # JSON has no NaN
        "id": f"{msg.arbitration_id:08X}",
        "data": bytes(msg.data).hex(),
        "kind": frame.kind.value,
        "direction": frame.direction.value if frame.direction else None,
        "abh3_id": frame.abh3,
        "host_id": frame.host,
        "priority": frame.priority,
    }
    if frame.abh3 is not None:
        channel = str(msg.channel or "")
        out["unit"] = names.get((channel, frame.abh3)) or names.get(("", frame.abh3))
    if frame.packet is not None:
        out["group"], out["packet"] = frame.group, frame.packet
    generation = book.generation(frame.abh3) if frame.abh3 is not None else None
    if generation is not None:
        out["protocol"] = generation.value
    layout = flags.layout(generation or book.default_generation)
    out["values"], out["flags"] = _values(frame, layout)
    if frame.abh3 is not None and any(k.endswith(("_ay", "_bx")) for k in out["values"]):
        channel = str(msg.channel or "")
        model = (models or {}).get((channel, frame.abh3)) or (models or {}).get(("", frame.abh3))
        if model is not None:  # what the AY/BX fields are: "Y/X" (travel) or "A/B" (motors)
            out["axes"] = readouts.axes(model)
    return out


def _values(
    frame: DecodedFrame, layout: flags.Layout
) -> tuple[dict[str, Any], dict[str, list[str]]]:
    """Physical values and the names of every set flag, in the drive's generation."""
    payload = frame.payload
    if isinstance(payload, frames.Unknown):
        return {"reason": payload.reason}, {}
    values: dict[str, Any] = {}
    for f in dataclasses.fields(payload):
        value = getattr(payload, f.name)
        if value is not None:
            values[f.name] = value.hex() if isinstance(value, bytes) else value
    if isinstance(payload, frames.Request):
        values["pgn"] = f"{payload.pgn:06X}"
        values["asks"] = (
            "dp0"
            if payload.is_dp0
            else (
                f"broadcast {payload.broadcast[1]} of group {payload.broadcast[0]}"
                if payload.broadcast
                else "other"
            )
        )
    if isinstance(payload, frames.Dp0Command):  # the unit says it: the booleans add nothing
        del values["ay_is_current"], values["bx_is_current"]
        values["ay_unit"] = "%" if payload.ay_is_current else "min^-1"
        values["bx_unit"] = "%" if payload.bx_is_current else "min^-1"
    words = layout.words
    named = {k: words[k].names(v) for k, v in values.items() if k in words and isinstance(v, int)}
    for key in named:
        values[key] = f"0x{values[key]:08X}"
    return values, named


def line(rec: dict[str, Any]) -> str:
    who = rec.get("unit") or (f"id{rec['abh3_id']}" if rec["abh3_id"] is not None else "-")
    axes = {"axes": rec["axes"]} if "axes" in rec else {}
    vals = " ".join(f"{k}={v}" for k, v in {**axes, **rec["values"]}.items())
    named = " ".join(f"{k}[{','.join(v)}]" for k, v in rec["flags"].items() if v)
    arrow = {"host->drive": "→", "drive->host": "←"}.get(rec["direction"] or "", " ")
    kind = rec["kind"] + (f"{rec['packet']}" if rec["kind"] == Kind.BROADCAST else "")
    t = "?" if rec["t"] is None else f"{rec['t']:.6f}"
    return f"{t} {rec['id']} {arrow} {who:<8} {kind:<12} {vals} {named}".rstrip()


HOST = 2  # the host address assumed without a configuration (AddressBook's default)


def inferred_books(path: Path, say: Callable[[str], None]) -> tuple[dict[str, AddressBook], Models]:
    """Without a configuration: each drive address's generation as ``abh3 scan`` reads it
    from the traffic (its DP0 replies' shape, its error word), one book per channel, and
    its velocity model where its control word says it. Says on ``say`` what it guessed, one
    line per address."""
    found = _traffic(path, say)
    books = {"": AddressBook()}
    models: Models = {}
    for channel, findings in sorted(found.items()):
        where = f" on {channel}" if len(found) > 1 and channel else ""
        generations = {}
        for d in sorted(findings.drives.values(), key=lambda d: d.address):
            if d.travel_model is not None:
                travel = VelocityModel.TRAVEL if d.travel_model else VelocityModel.MOTOR
                models[(channel, d.address)] = travel
            if d.generation is None:
                say(
                    f"decode: address {d.address}{where} sent no DP0 reply to tell its "
                    f"generation (no --config): decoded as {AddressBook().default_generation}"
                )
                continue
            generations[d.address] = d.generation
            why = "" if d.generation_certain else "; idle replies read alike in both"
            say(
                f"decode: address {d.address}{where} looks like a {d.generation} drive "
                f"(no --config{why}): guessed"
            )
        books[channel] = AddressBook(generations=generations)
    return books, models


def _traffic(path: Path, say: Callable[[str], None]) -> dict[str, Findings]:
    """A first pass over the file: what ``abh3 scan`` reads of each drive address from its
    traffic, per channel. What it cannot read is reported by the pass that decodes (or
    here, when nothing can be read)."""
    found: dict[str, Findings] = {}
    held: list[str] = []
    try:
        for msg in read_messages(path, held.append):
            if msg.is_error_frame or msg.is_remote_frame or not msg.is_extended_id:
                continue
            channel = str(msg.channel or "")
            findings = found.setdefault(channel, Findings(HOST))
            findings.observe(msg.arbitration_id, bytes(msg.data))
    except Abh3Error:
        for text in held:
            say(text)
        raise
    for findings in found.values():
        findings.finish()
    return found


def _against_file(
    path: Path, config: Config, books: dict[str, AddressBook], say: Callable[[str], None]
) -> None:
    """Say where the recording's traffic shows a drive surely of the other generation
    than the file gives its address: its frames, decoded as the file says, would show
    made-up flags (a recording read with another robot's file)."""
    for channel, findings in sorted(_traffic(path, say).items()):
        book = books.get(channel, books[""])
        for d in sorted(findings.drives.values(), key=lambda d: d.address):
            filed = book.generations.get(d.address)
            if d.generation is None or not d.generation_certain or filed in (None, d.generation):
                continue
            where = f" on {channel}" if channel else ""
            say(
                f"decode: address {d.address}{where} looks like a {d.generation} drive in "
                f"{path.name}, but {config.file} says {filed}: decoded as the file says — "
                "was the recording made with this file? (without --config each address is "
                "decoded as its traffic shows)"
            )


def decode_file(
    path: Path,
    config: Config | None,
    as_json: bool,
    report: Callable[[str], None] | None = None,
) -> Iterator[str]:
    """Every frame decoded, one line (or JSON object) each. Without ``config`` each drive
    address is decoded in the generation its traffic shows, said on ``report`` (stderr).
    Frames with AY/BX fields say which axes they are (``axes``) where the unit's model is
    known: from ``config``, else from the drive's control word."""
    say = report or _to_stderr
    if config is not None:
        books, models = address_books(config), velocity_models(config)
        _against_file(path, config, books, say)
    else:
        books, models = inferred_books(path, say)
    names = unit_names(config)
    for msg in read_messages(path, report):
        rec = record(msg, books, names, models)
        yield json.dumps(rec) if as_json else line(rec)
