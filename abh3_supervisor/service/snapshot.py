"""The live state of every unit and bus as plain JSON values (the ``state`` method)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from abh3_supervisor.core import readouts
from abh3_supervisor.protocol import frames

if TYPE_CHECKING:
    from abh3_supervisor.core.state import UnitState
    from abh3_supervisor.core.supervisor import Supervisor
    from abh3_supervisor.runtime.bus_runtime import Runtime
    from abh3_supervisor.scheduler.pump import BusPump


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _word(unit: UnitState, name: str, value: int) -> dict[str, Any]:
    """A flag word by value and set bits' names; an error or alarm word also says which
    set bits are normal for the unit's role, and what they mean there."""
    out: dict[str, Any] = {"value": value, "names": unit.layout.words[name].names(value)}
    if name in ("error", "alarm"):
        normal = readouts.read_faults(unit.cfg.role, value).normal
        out["notes"] = {b.name: readouts.fault_note(unit.cfg.role, b) for b in normal}
    return out


def _reported(unit: UnitState, control: int | None) -> dict[str, Any] | None:
    """Servo and start per axis [A/Y, B/X] as the drive last reported them, and when."""
    t = readouts.control_reported_at(unit)
    if control is None or t is None:
        return None
    seen = readouts.switches(unit.layout, control, t)
    return {"t": seen.t, "servo": list(seen.servo), "start": list(seen.start)}


def unit_state(sup: Supervisor, unit: UnitState) -> dict[str, Any]:
    slot = sup.schedulers[unit.cfg.bus].slots[unit.name]
    st, fb, now = slot.stats, unit.feedback, sup.clock()
    words = dict(unit.words)  # copied at once: the bus side may write meanwhile
    status: dict[str, Any] = {}
    for packet, (_, record) in dict(unit.status).items():
        if not isinstance(record, frames.Brd7):
            status[str(packet)] = dataclasses.asdict(record)
    return {
        "bus": unit.cfg.bus,
        "abh3_id": unit.cfg.abh3_id,
        "protocol": unit.cfg.protocol.value,
        "role": unit.cfg.role.value,
        "velocity_model": unit.cfg.velocity_model.value,
        "online": unit.online,
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
        "inputs": {"value": unit.inputs, "names": unit.layout.input.names(unit.inputs)},
        "words": {
            name: _word(unit, name, value)
            for name, value in words.items()
            if name in unit.layout.words
        },
        "reported": _reported(unit, words.get("control")),
        # the drive's CAN settings against the file (core/verify.py: Verification.to_json)
        "verify": unit.verify.to_json(),
        "status": status,
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
            "rtt_p50_ms": _finite(st.rtt_ms(50)),
            "rtt_p99_ms": _finite(st.rtt_ms(99)),
        },
    }


def state(rt: Runtime) -> dict[str, Any]:
    return supervisor_state(rt.supervisor, rt.pumps)


def _health(sup: Supervisor, bus: str) -> dict[str, Any]:
    """What the bus's interface reports of itself: ``ok``, ``bus-off``, … since when."""
    health = sup.bus_health[bus]
    return {"state": health.state.value, "since": health.since, "detail": health.detail}


def supervisor_state(sup: Supervisor, pumps: Mapping[str, BusPump]) -> dict[str, Any]:
    """The state of a supervisor and the pumps of its buses (none: a test's fake time)."""
    return {
        "t": sup.clock(),
        "estop": sup.estop,
        "stopping": sup.stopping,
        "units": {name: unit_state(sup, unit) for name, unit in sup.units.items()},
        "buses": {name: _bus(sup, name, pumps.get(name)) for name in sup.schedulers},
    }


def _bus(sup: Supervisor, name: str, pump: BusPump | None) -> dict[str, Any]:
    counts = ("frames_sent", "frames_received", "send_errors", "bus_errors")
    return {**{key: getattr(pump, key, 0) for key in counts}, **_health(sup, name)}
