"""Robots on two drives for the tests that drive them: one wheel per drive, and a
skid-steer (front A/B, rear A/B); and a spy on a bus's scheduler that records which
drives' command words each turn sent."""

from __future__ import annotations

import math

from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.protocol import frames
from abh3_supervisor.protocol.scaling import VELOCITY

# left drive limited below the right one: a straight twist saturates the left side first
TWO_DRIVES = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: l, abh3_id: 1, command_rate_hz: 50, velocity_model: motor,
     limits: {velocity: 1000}}
  - {name: r, abh3_id: 3, protocol: "2023", command_rate_hz: 50, velocity_model: motor,
     limits: {velocity: 3000}}
robots:
  - name: rover
    track_m: 0.5
    diameter_m: 0.3
    gear_ratio: 10
    wheels:
      - {unit: l, axis: A, side: left}
      - {unit: r, axis: A, side: right, sign: -1}
"""

SKID = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: front, abh3_id: 1, command_rate_hz: 50, velocity_model: motor}
  - {name: rear, abh3_id: 3, command_rate_hz: 50, velocity_model: motor}
robots:
  - name: skid
    track_m: 0.6
    diameter_m: 0.2
    gear_ratio: 5
    wheels:
      - {unit: front, axis: A, side: left}
      - {unit: front, axis: B, side: right, sign: -1}
      - {unit: rear, axis: A, side: left}
      - {unit: rear, axis: B, side: right, sign: -1}
"""


def motor(ground_mps: float, diameter_m: float, gear_ratio: float) -> float:
    """A wheel's motor speed [min⁻¹] for a ground speed, mounted forward."""
    return ground_mps * 60.0 * gear_ratio / (math.pi * diameter_m)


Turn = dict[str, tuple[float, float]]  # unit → the (AY, BX) its DP0 command carried


def turns(sup: Supervisor, bus: str = "b") -> list[Turn]:
    """Every turn of ``bus``'s scheduler from now on that sent a DP0 command: per unit,
    the velocities it carried (the scheduler's own poll, wrapped: a turn is one poll)."""
    sched = sup.schedulers[bus]
    ids = {slot.command_id: name for name, slot in sched.slots.items()}
    seen: list[Turn] = []
    real = sched.poll

    def spy(now: float) -> list[tuple[int, bytes]]:
        out = real(now)
        turn = {}
        for ident, data in out:
            if ident in ids:
                ay, bx, _ = frames.unpack_dp0_command(data)
                turn[ids[ident]] = (VELOCITY.to_physical(ay), VELOCITY.to_physical(bx))
        if turn:
            seen.append(turn)
        return out

    sched.poll = spy  # type: ignore[method-assign]
    return seen


def first_moving(seen: list[Turn]) -> Turn:
    """The first turn in which some drive's command was not zero."""
    return next(t for t in seen if any(v for pair in t.values() for v in pair))
