"""What ``abh3 fleet`` checks of each payload it reads, before the model takes it: the
size, JSON, ``v``/``time``/``seq``, and each field's type as the contract's schemas say
(``abh3_supervisor.fleet.schemas``; jsonschema is a test dependency, not the view's).
Topics, the payloads' building and the constants are ``abh3_supervisor.fleet``'s.
"""

from __future__ import annotations

import json
import math
from typing import Any

from abh3_supervisor.fleet.payloads import V

MAX_PAYLOAD = 64 * 1024  # bigger than any payload of the contract: not parsed at all


class Malformed(ValueError):
    """A payload that is not what the contract says (the text says what is wrong)."""


class WrongVersion(Malformed):
    """A payload of another contract version (``v`` not 1)."""


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
    if obj.get("v") != V:
        raise WrongVersion(f"version {obj.get('v')!r}, not {V}")
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
