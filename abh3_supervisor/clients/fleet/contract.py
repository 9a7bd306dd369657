"""The part of the fleet contract (docs/fleet.md) ``abh3 fleet`` reads and sends: topic
names, payload checks, the e-stop command. Pure: no MQTT client, no clock of its own.

Kept minimal and local until ``abh3_supervisor/fleet/`` (the contract's shared helpers)
is on main; then this defers to it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

VERSION = 1
PREFIX = "abh3/v1"
ALL = "all"  # the fleet_id level that addresses every robot (commands only)
STATES = ("online", "offline", "connection_broken")
MAX_PAYLOAD = 64 * 1024  # bigger than any payload of the contract: not parsed at all


class Malformed(ValueError):
    """A payload that is not what the contract says (the text says what is wrong)."""


class WrongVersion(Malformed):
    """A payload of another contract version (``v`` not 1)."""


@dataclass(frozen=True)
class Topic:
    """What a topic under the prefix is: ``kind`` one of status, state, events, health,
    command, vda (not ours to read) or unknown."""

    kind: str
    fleet_id: str
    unit: str | None = None


def parse_topic(topic: str, prefix: str = PREFIX) -> Topic | None:
    """The meaning of ``topic``; None when it is not under ``prefix``."""
    head = prefix.rstrip("/") + "/"
    if not topic.startswith(head):
        return None
    parts = topic[len(head) :].split("/")
    fid, rest = parts[0], parts[1:]
    if not fid:
        return Topic("unknown", "")
    if rest == ["status"]:
        return Topic("status", fid)
    if rest in (["events"], ["health"]):
        return Topic(rest[0], fid)
    if len(rest) == 3 and rest[0] == "units" and rest[2] == "state" and rest[1]:
        return Topic("state", fid, rest[1])
    if len(rest) == 2 and rest[0] == "cmd":
        return Topic("command", fid)
    return Topic("unknown", fid)


def decode(payload: bytes) -> dict[str, Any]:
    """A payload's JSON object, checked for what every payload carries (v, time, seq)."""
    if len(payload) > MAX_PAYLOAD:
        raise Malformed(f"over {MAX_PAYLOAD} bytes: larger than any payload of the contract")
    try:
        obj = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise Malformed(f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise Malformed("not a JSON object")
    if obj.get("v") != VERSION:
        raise WrongVersion(f"version {obj.get('v')!r}, not {VERSION}")
    number(obj, "time")
    seq = obj.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 1:
        raise Malformed(f"seq {seq!r} is not a positive integer")
    return obj


def number(obj: dict[str, Any], key: str, *, none: bool = False) -> float | None:
    value = obj.get(key)
    if value is None and none and key in obj:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise Malformed(f"{key} {value!r} is not a number")
    return float(value)


def text(obj: dict[str, Any], key: str, *, none: bool = False) -> str | None:
    value = obj.get(key)
    if value is None and none and key in obj:
        return None
    if not isinstance(value, str):
        raise Malformed(f"{key} {value!r} is not a string")
    return value


def flag(value: object, key: str) -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    raise Malformed(f"{key} {value!r} is not true, false or null")


def names(obj: dict[str, Any], key: str) -> tuple[str, ...]:
    value = obj.get(key)
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise Malformed(f"{key} {value!r} is not a list of names")
    return tuple(value)


def pair(obj: dict[str, Any], key: str) -> tuple[bool | None, bool | None]:
    value = obj.get(key)
    if not isinstance(value, list) or len(value) != 2:
        raise Malformed(f"{key} {value!r} is not a pair")
    return flag(value[0], key), flag(value[1], key)


def axes(obj: dict[str, Any], key: str, letters: tuple[str, str]) -> tuple[float | None, ...]:
    value = obj.get(key)
    if not isinstance(value, dict):
        raise Malformed(f"{key} {value!r} is not an object")
    try:
        return tuple(number(value, k, none=True) for k in letters)
    except Malformed as exc:
        raise Malformed(f"{key}.{exc}") from None


def command_topic(prefix: str, fleet_id: str | None, clear: bool) -> str:
    """``{prefix}/{fleet_id}/cmd/estop`` (or ``estop_clear``); ``fleet_id`` None: all."""
    kind = "estop_clear" if clear else "estop"
    return f"{prefix.rstrip('/')}/{fleet_id or ALL}/cmd/{kind}"


def estop_command(sender: str, seq: int, reason: str, now: float) -> bytes:
    """An ``estop_command`` payload (the same for e-stop and clear: the topic says which)."""
    body = {"v": VERSION, "time": now, "seq": seq, "sender": sender, "reason": reason}
    return json.dumps(body, separators=(",", ":")).encode()
