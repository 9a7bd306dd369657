"""The live state of every unit and bus as plain JSON values (the ``state`` method)."""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from abh3_supervisor.core import readouts
from abh3_supervisor.protocol import frames
from abh3_supervisor.service.protocol import dumps

if TYPE_CHECKING:
    from abh3_supervisor.config.model import Role
    from abh3_supervisor.core.state import UnitState
    from abh3_supervisor.core.supervisor import Supervisor
    from abh3_supervisor.core.verify import Verification
    from abh3_supervisor.protocol.flags import FlagWord
    from abh3_supervisor.runtime.bus_runtime import Runtime
    from abh3_supervisor.scheduler.pump import BusPump


_FIELDS: dict[type, tuple[str, ...]] = {}


def _record(record: object) -> dict[str, Any]:
    """A flat status record as a dict: ``dataclasses.asdict`` deep-copies every value,
    which made it most of a snapshot's cost."""
    kind = type(record)
    if (names := _FIELDS.get(kind)) is None:
        names = _FIELDS[kind] = tuple(f.name for f in dataclasses.fields(kind))  # type: ignore[arg-type]
    return {name: getattr(record, name) for name in names}


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _flag_words(unit: UnitState, words: dict[str, int]) -> Iterator[tuple[FlagWord, str, int]]:
    """The unit's flag words its layout names (word, name, value), in the order they came."""
    layout = unit.layout.words
    return ((layout[name], name, value) for name, value in words.items() if name in layout)


@functools.lru_cache(maxsize=1024)
def _word_json(word: FlagWord, role: Role, name: str, value: int) -> dict[str, Any]:
    """A flag word by value and set bits' names; an error or alarm word also says which
    set bits are normal for the unit's role, and what they mean there. The same few
    values recur on every push: each is worked out once (callers never mutate it)."""
    out: dict[str, Any] = {"value": value, "names": word.names(value)}
    if name in ("error", "alarm"):
        normal = readouts.read_faults(role, value).normal
        out["notes"] = {b.name: readouts.fault_note(role, b) for b in normal}
    return out


@functools.lru_cache(maxsize=256)
def _verify_json(verification: Verification) -> dict[str, Any]:
    """A unit's verification (frozen: a new check is a new object) as JSON, once."""
    return verification.to_json()


@functools.lru_cache(maxsize=256)
def _verify_encoded(verification: Verification) -> bytes:
    """The same, encoded: about half of a unit's pushed bytes, the same on every push."""
    return dumps(_verify_json(verification))


@functools.lru_cache(maxsize=1024)
def _word_encoded(word: FlagWord, role: Role, name: str, value: int) -> bytes:
    """``"name":{…}``: a flag word's member of ``words``, encoded once per value."""
    return dumps(name) + b":" + dumps(_word_json(word, role, name, value))


@functools.lru_cache(maxsize=1024)
def _flags_encoded(word: FlagWord, value: int) -> bytes:
    return dumps(_flags(word, value))


def _flags(word: FlagWord, value: int) -> dict[str, Any]:
    return {"value": value, "names": word.names(value)}


def unit_json(sup: Supervisor, unit: UnitState) -> bytes:
    """:func:`unit_state` encoded (the pushed state, 10 times a second): its flag words,
    its verification and its status records, which mostly keep their values from one
    push to the next, are spliced in encoded once per value."""
    words = dict(unit.words)  # copied at once: the bus side may write meanwhile
    role = unit.cfg.role
    return b"".join(
        (
            dumps(_unit_changing(sup, unit, words))[:-1],  # the object left open
            b',"inputs":',
            _flags_encoded(unit.layout.input, unit.inputs),
            b',"words":{',
            b",".join(
                _word_encoded(w, role, name, value) for w, name, value in _flag_words(unit, words)
            ),
            b'},"verify":',
            _verify_encoded(unit.verify),
            b',"status":{',
            b",".join(_record_encoded(packet, record) for packet, record in _status(unit)),
            b"}}",
        )
    )


def _reported(unit: UnitState, control: int | None) -> dict[str, Any] | None:
    """Servo and start per axis [A/Y, B/X] as the drive last reported them, and when."""
    t = readouts.control_reported_at(unit)
    if control is None or t is None:
        return None
    seen = readouts.switches(unit.layout, control, t)
    return {"t": seen.t, "servo": list(seen.servo), "start": list(seen.start)}


def unit_state(sup: Supervisor, unit: UnitState) -> dict[str, Any]:
    words = dict(unit.words)  # copied at once: the bus side may write meanwhile
    return {
        **_unit_changing(sup, unit, words),
        "inputs": _flags(unit.layout.input, unit.inputs),
        "words": {
            name: _word_json(word, unit.cfg.role, name, value)
            for word, name, value in _flag_words(unit, words)
        },
        # the drive's CAN settings against the file (core/verify.py: Verification.to_json)
        "verify": _verify_json(unit.verify),
        "status": {str(packet): _record(record) for packet, record in _status(unit)},
    }


def _status(unit: UnitState) -> list[tuple[int, frames.Broadcast]]:
    """The last broadcast packets (the 8th, a 2023 drive's parameter answer, aside)."""
    return [(p, r) for p, (_, r) in dict(unit.status).items() if not isinstance(r, frames.Brd7)]


@functools.lru_cache(maxsize=1024)
def _record_encoded(packet: int, record: frames.Broadcast) -> bytes:
    """``"packet":{…}``: frozen, compared by value; most are unchanged between pushes."""
    return dumps(str(packet)) + b":" + dumps(_record(record))


def _unit_changing(sup: Supervisor, unit: UnitState, words: dict[str, int]) -> dict[str, Any]:
    """A unit's state but its flag words, its inputs, its verification and its status."""
    slot = sup.schedulers[unit.cfg.bus].slots[unit.name]
    st, fb, now = slot.stats, unit.feedback, sup.clock()
    rtt_p50, rtt_p99 = st.rtts_ms(50, 99)
    return {
        "bus": unit.cfg.bus,
        "abh3_id": unit.cfg.abh3_id,
        "protocol": unit.cfg.protocol.value,
        "role": unit.cfg.role.value,
        "velocity_model": unit.cfg.velocity_model.value,
        "online": unit.online,
        # the generation its replies show (None: not yet): another than the file's holds it
        "identified": None if unit.identified is None else str(unit.identified),
        "setpoint": {
            "kind": unit.setpoint.kind.value,
            "ay": unit.setpoint.ay,
            "bx": unit.setpoint.bx,
        },
        "feedback": None
        if fb is None
        else {
            "t": fb.t,
            "vel_a": fb.vel_a,
            "vel_b": fb.vel_b,
            "vel_y": fb.vel_y,
            "vel_x": fb.vel_x,
            "control": fb.control,
        },
        "reported": _reported(unit, words.get("control")),
        # other hosts on the unit's drive (core/foreign.py) and the stop they caused
        "foreign": {
            "stopped": sup.gate.foreign.get(unit.name),
            "hosts": [host.to_json() for host in sup.foreign_hosts(unit.name)],
        },
        "stats": {
            "rate_hz": st.achieved_rate_hz(now),
            "requested_rate_hz": st.requested_rate_hz,
            "replies": st.replies,
            "commands_sent": st.commands_sent,
            "broadcasts": st.broadcasts,
            "timeouts": st.timeouts,
            "send_errors": st.send_errors,
            "malformed": st.malformed,
            "gaps": st.gaps,
            "rtt_p50_ms": _finite(rtt_p50),
            "rtt_p99_ms": _finite(rtt_p99),
        },
    }


def state(rt: Runtime, slowed: dict[str, Any] | None = None) -> dict[str, Any]:
    return supervisor_state(rt.supervisor, rt.pumps, slowed)


def _health(sup: Supervisor, bus: str) -> dict[str, Any]:
    """What the bus's interface reports of itself: ``ok``, ``bus-off``, … since when."""
    health = sup.bus_health[bus]
    return {"state": health.state.value, "since": health.since, "detail": health.detail}


def head(sup: Supervisor, slowed: dict[str, Any] | None = None) -> dict[str, Any]:
    """What a state says before its units: when, the supervisor's own switches, and
    whether pushes give way to late buses (``slowed``: service/view_pace.py)."""
    return {
        "t": sup.clock(),
        "estop": sup.estop,
        "stopping": sup.stopping,
        "slowed": slowed,
        "robots": sup.readiness(),
    }


def supervisor_state(
    sup: Supervisor, pumps: Mapping[str, BusPump], slowed: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The state of a supervisor and the pumps of its buses (none: a test's fake time)."""
    return {
        **head(sup, slowed),
        "units": {name: unit_state(sup, unit) for name, unit in sup.units.items()},
        "buses": {name: bus_state(sup, name, pumps.get(name)) for name in sup.schedulers},
    }


def bus_state(sup: Supervisor, name: str, pump: BusPump | None) -> dict[str, Any]:
    counts = ("frames_sent", "frames_received", "send_errors", "bus_errors")
    return {**{key: getattr(pump, key, 0) for key in counts}, **_health(sup, name)}
