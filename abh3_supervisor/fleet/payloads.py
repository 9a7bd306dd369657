"""Every payload of the contract, built from plain values, and the commands parsed and
judged (docs/fleet.md, "Payloads" and "Commands"). Pure: the caller brings the clock."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from abh3_supervisor.fleet.topics import VDA_VERSION

V = 1
STATES = ("online", "offline", "connection_broken")
VDA_STATES = {"online": "ONLINE", "offline": "OFFLINE", "connection_broken": "CONNECTIONBROKEN"}
MAX_COMMAND_BYTES = 4096  # any command of ours is far shorter: larger is refused unread
MAX_TEXT = 200  # sender and reason, as kept for the audit


class Sequence:
    """``seq`` per topic, from 1, +1 per message built; thread-safe (several threads
    build messages for one connection)."""

    def __init__(self) -> None:
        self._next: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, topic: str) -> int:
        with self._lock:
            n = self._next.get(topic, 1)
            self._next[topic] = n + 1
            return n


def stamped(seq: int, now: float, body: dict[str, Any]) -> dict[str, Any]:
    """``body`` after ``v``, ``time`` and ``seq``."""
    return {"v": V, "time": now, "seq": seq, **body}


def encode(payload: dict[str, Any]) -> bytes:
    """UTF-8 JSON, compact; a non-finite number is a bug here, never sent as ``NaN``."""
    return json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()


def status(
    seq: int,
    now: float,
    *,
    fleet_id: str,
    robot: str,
    state: str,
    host: str,
    pid: int,
    version: str,
    units: list[str],
    attach: str | None = None,
) -> dict[str, Any]:
    if state not in STATES:
        raise ValueError(f"status {state!r} is not one of {', '.join(STATES)}")
    return stamped(
        seq,
        now,
        {
            "fleet_id": fleet_id,
            "robot": robot,
            "state": state,
            "host": host,
            "pid": pid,
            "version": version,
            "units": units,
            "attach": attach,
        },
    )


def _num(value: float | None) -> float | None:
    """A JSON number, or null for none or a non-finite one."""
    return None if value is None or not math.isfinite(value) else float(value)


@dataclass(frozen=True)
class UnitReport:
    """One unit's state as the supervisor has it, in the contract's words."""

    unit: str
    online: bool | None
    servo: tuple[bool | None, bool | None] = (None, None)
    start: tuple[bool | None, bool | None] = (None, None)
    commanded: tuple[float, float] = (0.0, 0.0)  # ay, bx
    measured: tuple[float | None, float | None] = (None, None)  # a, b
    errors: tuple[str, ...] = ()
    alarms: tuple[str, ...] = ()
    owner: str | None = None
    estop: bool = False
    verify: str = "unknown"
    foreign_host: tuple[int, int] | None = None  # address, frames
    age_s: float | None = None

    def safety(self) -> tuple[Any, ...]:
        """What a change of publishes the state at once (docs/fleet.md): another host's
        address, not its count of frames (that goes out at the state's rate)."""
        return (
            self.online,
            self.servo,
            self.start,
            self.errors,
            self.alarms,
            self.owner,
            self.estop,
            self.verify,
            None if self.foreign_host is None else self.foreign_host[0],
        )


def unit_state(
    seq: int, now: float, *, fleet_id: str, robot: str, report: UnitReport
) -> dict[str, Any]:
    r = report
    return stamped(
        seq,
        now,
        {
            "fleet_id": fleet_id,
            "robot": robot,
            "unit": r.unit,
            "online": r.online,
            "servo": list(r.servo),
            "start": list(r.start),
            "commanded": {"ay": _num(r.commanded[0]) or 0.0, "bx": _num(r.commanded[1]) or 0.0},
            "measured": {"a": _num(r.measured[0]), "b": _num(r.measured[1])},
            "errors": list(r.errors),
            "alarms": list(r.alarms),
            "owner": r.owner,
            "estop": r.estop,
            "verify": r.verify,
            "foreign_host": None
            if r.foreign_host is None
            else {"address": r.foreign_host[0], "frames": r.foreign_host[1]},
            "age_s": _num(r.age_s),
        },
    )


def event(
    seq: int,
    now: float,
    *,
    fleet_id: str,
    robot: str,
    unit: str | None,
    kind: str,
    text: str,
    data: dict[str, Any] | None = None,
) -> dict[str, Any]:
    return stamped(
        seq,
        now,
        {
            "fleet_id": fleet_id,
            "robot": robot,
            "unit": unit,
            "kind": kind,
            "text": text,
            "data": data or {},
        },
    )


def health(
    seq: int,
    now: float,
    *,
    fleet_id: str,
    robot: str,
    buses: dict[str, dict[str, Any]],
    queued: int,
    dropped: int,
    reconnects: int,
    not_heard: list[str] | None = None,
) -> dict[str, Any]:
    """``not_heard``: the fleet's commands (``estop``, ``twist``, ``instant_actions``: the
    VDA 5050 ones) the robot cannot hear, their connection or subscription refused by the
    broker."""
    return stamped(
        seq,
        now,
        {
            "fleet_id": fleet_id,
            "robot": robot,
            "buses": buses,
            "mqtt": {
                "queued": queued,
                "dropped": dropped,
                "reconnects": reconnects,
                "not_heard": sorted(not_heard or []),
            },
        },
    )


def estop_command(seq: int, now: float, *, sender: str, reason: str) -> dict[str, Any]:
    return stamped(seq, now, {"sender": sender, "reason": reason})


def twist_command(
    seq: int, now: float, *, sender: str, linear: float, angular: float
) -> dict[str, Any]:
    return stamped(seq, now, {"sender": sender, "linear": linear, "angular": angular})


# ---------------------------------------------------------------- VDA 5050


def iso(now: float) -> str:
    """VDA 5050's timestamp: ISO 8601, UTC, milliseconds, ``Z``."""
    stamp = datetime.fromtimestamp(now, UTC)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S.") + f"{stamp.microsecond // 1000:03d}Z"


def vda_header(header_id: int, now: float, manufacturer: str, fleet_id: str) -> dict[str, Any]:
    return {
        "headerId": header_id,
        "timestamp": iso(now),
        "version": VDA_VERSION,
        "manufacturer": manufacturer,
        "serialNumber": fleet_id,
    }


def vda_connection(
    header_id: int, now: float, *, manufacturer: str, fleet_id: str, state: str
) -> dict[str, Any]:
    """The VDA 5050 ``connection`` message of our ``status`` state."""
    return {
        **vda_header(header_id, now, manufacturer, fleet_id),
        "connectionState": VDA_STATES[state],
    }


def vda_instant_actions(
    header_id: int, now: float, *, manufacturer: str, fleet_id: str, actions: list[str]
) -> dict[str, Any]:
    """An ``instantActions`` message of ``actions`` (``startPause``, ``stopPause``): what a
    master control sends (``abh3 fleet`` and the tests)."""
    return {
        **vda_header(header_id, now, manufacturer, fleet_id),
        "actions": [
            {"actionType": a, "actionId": f"abh3-{header_id}-{i}", "blockingType": "HARD"}
            for i, a in enumerate(actions)
        ],
    }


# ---------------------------------------------------------------- commands


class Refused(ValueError):
    """A command not to obey; the text says why (the ``fleet_command_refused`` event)."""


@dataclass(frozen=True)
class Command:
    """A command parsed, its time judged; its ``seq`` still to be (:class:`SeqGuard`)."""

    kind: str  # estop, estop_clear, twist
    sender: str
    seq: int
    time: float
    reason: str = ""
    linear: float = 0.0
    angular: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)  # for the audit and the event


def _decode(raw: bytes | bytearray) -> Any:
    if len(raw) > MAX_COMMAND_BYTES:
        raise Refused(f"{len(raw)} bytes: larger than any command ({MAX_COMMAND_BYTES})")
    try:
        return json.loads(raw.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError) as exc:
        raise Refused(f"not JSON: {exc}") from None


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _field(body: dict[str, Any], key: str, kinds: tuple[type, ...]) -> Any:
    value = body.get(key)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        got = "missing" if key not in body else type(value).__name__
        raise Refused(f"'{key}': {got}, wanted {' or '.join(k.__name__ for k in kinds)}")
    return value


def fresh(t: float, now: float, timeout_s: float) -> None:
    """A command's time against ours: not older than ``timeout_s``, nor ahead by more."""
    if not math.isfinite(t):
        raise Refused("its time is not a finite number")
    if t < now - timeout_s:
        raise Refused(f"stale: {now - t:.3f} s old (command_timeout_ms {timeout_s * 1000:g})")
    if t > now + timeout_s:
        raise Refused(f"from the future: {t - now:.3f} s ahead of our clock")


def _text(value: str) -> str:
    return "".join(c if c.isprintable() else "?" for c in value)[:MAX_TEXT]


def parse_command(
    kind: str,
    raw: bytes | bytearray,
    *,
    now: float,
    timeout_s: float,
    retained: bool,
    sender_property: str | None = None,
) -> Command:
    """An ``estop_command`` or ``twist_command`` (``kind``: estop, estop_clear, twist),
    or :class:`Refused`: retained, malformed, stale, from the future. The sender is the
    MQTT 5 user property ``sender`` when there is one, else the payload's."""
    if retained:
        raise Refused("retained: a command replayed by the broker is never obeyed")
    body = _decode(raw)
    if not isinstance(body, dict):
        raise Refused("not a JSON object")
    if body.get("v") != V:
        raise Refused(f"'v': {body.get('v')!r}, this robot speaks v{V}")
    seq = _field(body, "seq", (int,))
    if seq < 1:
        raise Refused(f"'seq': {seq}: counts from 1")
    t = float(_field(body, "time", (int, float)))
    said = _text(_field(body, "sender", (str,)))
    sender = _text(sender_property) if sender_property else said
    extra = {"payload_sender": said} if sender != said else {}
    if kind == "twist":
        linear = float(_field(body, "linear", (int, float)))
        angular = float(_field(body, "angular", (int, float)))
        if not (math.isfinite(linear) and math.isfinite(angular)):
            raise Refused("linear and angular must be finite numbers")
        fresh(t, now, timeout_s)
        return Command(kind, sender, seq, t, linear=linear, angular=angular, extra=extra)
    if kind not in ("estop", "estop_clear"):
        raise ValueError(f"no command {kind!r}")
    reason = _text(_field(body, "reason", (str,)))
    fresh(t, now, timeout_s)
    return Command(kind, sender, seq, t, reason=reason, extra=extra)


def parse_instant_actions(
    raw: bytes | bytearray,
    *,
    now: float,
    timeout_s: float,
    retained: bool,
    manufacturer: str,
    fleet_id: str,
    sender_property: str | None = None,
) -> tuple[list[Command], list[str]]:
    """A VDA 5050 ``instantActions`` message: its ``startPause`` (→ ``estop``) and
    ``stopPause`` (→ ``estop_clear``) as commands, and why each other action is not done.
    The whole message is :class:`Refused` when retained, malformed, stale, or not ours."""
    if retained:
        raise Refused("retained: a command replayed by the broker is never obeyed")
    body = _decode(raw)
    if not isinstance(body, dict):
        raise Refused("not a JSON object")
    seq = _field(body, "headerId", (int,))
    stamp = _field(body, "timestamp", (str,))
    try:
        when = datetime.fromisoformat(stamp)
    except ValueError:
        raise Refused(f"'timestamp' {stamp[:40]!r} is not ISO 8601") from None
    if when.tzinfo is None:
        raise Refused(f"'timestamp' {stamp[:40]!r} has no time zone (VDA 5050: UTC, Z)")
    for key, ours in (("manufacturer", manufacturer), ("serialNumber", fleet_id)):
        if _field(body, key, (str,)) != ours:
            raise Refused(f"'{key}' {body[key][:60]!r} is not this robot's ({ours})")
    _field(body, "version", (str,))
    actions = _field(body, "actions", (list,))
    t = when.timestamp()
    sender = _text(sender_property) if sender_property else f"vda5050 {manufacturer}"
    out: list[Command] = []
    skipped: list[str] = []
    for action in actions:
        if not isinstance(action, dict):
            raise Refused("an action is not a JSON object")
        kind = _field(action, "actionType", (str,))
        action_id = _text(_field(action, "actionId", (str,)))
        if action.get("blockingType") not in ("NONE", "SOFT", "HARD"):
            raise Refused(f"action {action_id}: 'blockingType' not NONE, SOFT or HARD")
        mapped = {"startPause": "estop", "stopPause": "estop_clear"}.get(kind)
        if mapped is None:
            skipped.append(f"{_text(kind)} ({action_id}): not an action of a drive supervisor")
            continue
        reason = f"VDA 5050 instantActions {kind} ({action_id})"
        out.append(Command(mapped, sender, seq, t, reason=reason, extra={"actionId": action_id}))
    fresh(t, now, timeout_s)
    return out, skipped


class SeqGuard:
    """Each sender's ``seq`` per topic must rise. A sender that starts again (its ``seq``
    from 1 on a new connection) is known by its time: more than ``timeout_s`` after the
    last command obeyed from it there (an older one is refused as stale anyway)."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self._last: dict[tuple[str, str], tuple[int, float]] = {}
        self._lock = threading.Lock()

    def admit(self, topic: str, command: Command) -> None:
        """Raise :class:`Refused` for a ``seq`` not above the last obeyed; else remember it."""
        key = (command.sender, topic)
        with self._lock:
            last = self._last.get(key)
            if (
                last is not None
                and command.seq <= last[0]
                and command.time <= last[1] + self.timeout_s
            ):
                raise Refused(f"seq {command.seq} not above {last[0]}, the last obeyed from it")
            self._last[key] = (command.seq, command.time)
