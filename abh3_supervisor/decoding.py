"""``abh3 decode``: an ABH3-aware reading of a recording made by ``--record``."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can

from abh3_supervisor.config.model import Config
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.classify import AddressBook, DecodedFrame, Kind, classify


def address_book(config: Config | None) -> AddressBook:
    if config is None:
        return AddressBook()
    return AddressBook(
        hosts=frozenset(u.host_id for u in config.units.values()),
        generations={u.abh3_id: u.protocol for u in config.units.values()},
    )


def unit_names(config: Config | None) -> dict[tuple[str, int], str]:
    """(channel, abh3_id) → unit name; channel '' matches any when the id is unique."""
    if config is None:
        return {}
    names: dict[tuple[str, int], str] = {}
    for u in config.units.values():
        names[(config.buses[u.bus].channel, u.abh3_id)] = u.name
        names[("", u.abh3_id)] = u.name if ("", u.abh3_id) not in names else "?"
    return names


def read_messages(path: Path) -> Iterator[can.Message]:
    try:
        yield from can.LogReader(str(path))
    except (OSError, ValueError) as exc:
        raise Abh3Error(f"{path}: cannot read recording: {exc}") from exc


def record(
    msg: can.Message, book: AddressBook, names: dict[tuple[str, int], str]
) -> dict[str, Any]:
    frame = classify(msg.arbitration_id, bytes(msg.data), msg.is_extended_id, book)
    out: dict[str, Any] = {
        "t": msg.timestamp,
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
    vals = " ".join(f"{k}={v}" for k, v in rec["values"].items())
    named = " ".join(f"{k}[{','.join(v)}]" for k, v in rec["flags"].items() if v)
    arrow = {"host->drive": "→", "drive->host": "←"}.get(rec["direction"] or "", " ")
    kind = rec["kind"] + (f"{rec['packet']}" if rec["kind"] == Kind.BROADCAST else "")
    return f"{rec['t']:.6f} {rec['id']} {arrow} {who:<8} {kind:<12} {vals} {named}".rstrip()


def decode_file(path: Path, config: Config | None, as_json: bool) -> Iterator[str]:
    book, names = address_book(config), unit_names(config)
    for msg in read_messages(path):
        rec = record(msg, book, names)
        yield json.dumps(rec) if as_json else line(rec)
