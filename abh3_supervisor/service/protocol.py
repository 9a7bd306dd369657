"""The control endpoint's wire protocol: JSON-RPC 2.0, one JSON object per line.

Why this encoding: JSON-RPC 2.0 is a published standard with request ids, notifications
and error codes already defined, so any language's stock library speaks it; one object per
line (UTF-8, ``\\n``-terminated) needs no framing beyond ``readline`` and can be typed by
hand into ``socat - UNIX-CONNECT:…``. The state we carry (a few kB at a few Hz) gains
nothing from a binary encoding. ``PROTOCOL`` is bumped on any incompatible change and
said in ``hello``; docs/service.md is the reference.
"""

from __future__ import annotations

import contextlib
import json
import math
from dataclasses import dataclass
from typing import Any

from abh3_supervisor.core.text import clean

PROTOCOL = 1
MAX_LINE = 64 * 1024  # a request is a few hundred bytes; anything longer is refused
SHOWN = 80  # characters of a client's own text quoted back in an error

# JSON-RPC 2.0's codes, and ours in its server-error range
PARSE_ERROR = -32700
INVALID_REQUEST = -32600
METHOD_NOT_FOUND = -32601
INVALID_PARAMS = -32602
INTERNAL_ERROR = -32603  # a fault of ours while answering: logged, the connection goes on
READ_ONLY = -32001  # a command on a read-only connection
REFUSED = -32002  # the supervisor refused it (unknown unit, e-stop latched, stopping, …)
# "bye"'s reason of an orderly stop: told before the supervisor stops its drives itself
STOPPING = "the supervisor is stopping"


class RpcError(Exception):
    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code, self.message = code, message


@dataclass(frozen=True, slots=True)
class Request:
    id: int | str | None  # None: a notification (no reply wanted)
    method: str
    params: dict[str, Any]


def parse_request(line: bytes) -> Request:
    """One line from a client; :class:`RpcError` says what is wrong with it, whatever it
    holds (invalid UTF-8, nesting deeper than the parser goes, an integer past Python's
    4300-digit conversion limit, which ``json`` raises as a bare ``ValueError``)."""
    try:
        message = json.loads(line.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise RpcError(PARSE_ERROR, f"not UTF-8: byte {exc.start}") from None
    except RecursionError:
        raise RpcError(PARSE_ERROR, "not JSON: nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, and the integer digit limit
        raise RpcError(PARSE_ERROR, f"not JSON: {shown(str(exc))}") from None
    if not isinstance(message, dict) or message.get("jsonrpc") != "2.0":
        raise RpcError(INVALID_REQUEST, 'expected a JSON-RPC 2.0 object ("jsonrpc": "2.0")')
    method, params, rid = message.get("method"), message.get("params", {}), message.get("id")
    if not isinstance(method, str):
        raise RpcError(INVALID_REQUEST, "'method' must be a string")
    if rid is not None and (isinstance(rid, bool) or not isinstance(rid, int | str)):
        raise RpcError(INVALID_REQUEST, "'id' must be a number or a string")
    if not isinstance(params, dict):
        raise RpcError(INVALID_PARAMS, "'params' must be an object")
    return Request(rid, method, params)


def request_id(line: bytes) -> int | str | None:
    """The id of a request we could not accept, if one can be read (for the error reply)."""
    try:
        rid = json.loads(line.decode("utf-8")).get("id")
    except Exception:
        return None
    return rid if isinstance(rid, int | str) and not isinstance(rid, bool) else None


def shown(text: str) -> str:
    """A client's own text quoted back in an error: escaped and capped as in a log line."""
    return clean(text, SHOWN)


class LineSplitter:
    """Bytes from a client in, complete lines out, blank ones left out. A line longer than
    ``MAX_LINE`` comes out as ``None`` (once, as soon as it is too long) and the rest of it,
    up to its newline, is dropped, so the connection goes on with the next line; what is
    buffered never passes ``MAX_LINE``. Split in C (``bytes.split``): 64 KiB of newlines
    cost 56 ms a line at a time."""

    def __init__(self, limit: int = MAX_LINE) -> None:
        self.limit = limit
        self._buf = bytearray()
        self._dropping = False

    def feed(self, data: bytes) -> list[bytes | None]:
        parts = data.split(b"\n")
        lines: list[bytes | None] = []
        if len(parts) > 1:  # the line in progress ends with the first part
            if not self._dropping:
                self._buf += parts[0]
                if len(self._buf) > self.limit:
                    lines.append(None)
                elif self._buf.strip():
                    lines.append(bytes(self._buf))
            self._buf.clear()
            self._dropping = False
            limit = self.limit
            lines += [p if len(p) <= limit else None for p in parts[1:-1] if p and not p.isspace()]
        if not self._dropping:  # the last part begins the next line
            self._buf += parts[-1]
            if len(self._buf) > self.limit:
                lines.append(None)
                self._buf.clear()
                self._dropping = True
        return lines


def dumps(value: Any) -> bytes:
    """Compact JSON, finite numbers only (every message is one line of it)."""
    return json.dumps(value, separators=(",", ":"), allow_nan=False).encode()


def encode(message: dict[str, Any]) -> bytes:
    return dumps(message) + b"\n"


def result(rid: int | str | None, value: Any) -> bytes:
    return encode({"jsonrpc": "2.0", "id": rid, "result": value})


def error(rid: int | str | None, code: int, message: str) -> bytes:
    return encode({"jsonrpc": "2.0", "id": rid, "error": {"code": code, "message": message}})


def notification(method: str, params: dict[str, Any]) -> bytes:
    return encode({"jsonrpc": "2.0", "method": method, "params": params})


# ---------------------------------------------------------------- reading params


def text(params: dict[str, Any], key: str) -> str:
    value = params.get(key)
    if not isinstance(value, str):
        raise RpcError(INVALID_PARAMS, f"'{key}' must be a string")
    return value


def number(params: dict[str, Any], key: str) -> float:
    value = params.get(key)
    if isinstance(value, int | float) and not isinstance(value, bool):
        with contextlib.suppress(OverflowError):  # an integer beyond a float's range
            if math.isfinite(converted := float(value)):
                return converted
    raise RpcError(INVALID_PARAMS, f"'{key}' must be a finite number")


def names(params: dict[str, Any], one: str, many: str) -> tuple[str, ...]:
    """``one`` (a name) or ``many`` (a list of names), in order, each once."""
    raw = params.get(many, [params[one]] if one in params else None)
    if not isinstance(raw, list) or not raw or not all(isinstance(u, str) for u in raw):
        raise RpcError(INVALID_PARAMS, f"give '{one}' (a name) or '{many}' (a list of names)")
    return tuple(dict.fromkeys(raw))


def units(params: dict[str, Any], known: tuple[str, ...]) -> tuple[str, ...]:
    """``unit`` (one name) or ``units`` (a list), each a declared unit."""
    raw = names(params, "unit", "units")
    unknown = [u for u in raw if u not in known]
    if unknown:
        raise RpcError(REFUSED, f"no unit named {shown(unknown[0])!r} (units: {', '.join(known)})")
    return raw
