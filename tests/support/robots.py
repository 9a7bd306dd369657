"""Robots on two drives for the tests that drive them: one wheel per drive, and a
skid-steer (front A/B, rear A/B); and a spy on a bus's scheduler that records which
drives' command words each turn sent."""

from __future__ import annotations

import math
from dataclasses import dataclass

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


@dataclass(frozen=True, slots=True)
class Sent:
    """A DP0 command the scheduler sent: when (its clock), to which unit, its AY/BX."""

    t: float
    unit: str
    ay: float
    bx: float


def sent(sup: Supervisor, bus: str = "b") -> list[Sent]:
    """Every DP0 command ``bus``'s scheduler sends from now on (its poll, wrapped)."""
    sched = sup.schedulers[bus]
    ids = {slot.command_id: name for name, slot in sched.slots.items()}
    seen: list[Sent] = []
    real = sched.poll

    def spy(now: float) -> list[tuple[int, bytes]]:
        out = real(now)
        for ident, data in out:
            if ident in ids:
                ay, bx, _ = frames.unpack_dp0_command(data)
                seen.append(
                    Sent(now, ids[ident], VELOCITY.to_physical(ay), VELOCITY.to_physical(bx))
                )
        return out

    sched.poll = spy  # type: ignore[method-assign]
    return seen


def first_moving(seen: list[Sent], units: tuple[str, ...]) -> dict[str, Sent] | None:
    """Each unit's first command that was not zero, once every one of ``units`` had one."""
    first: dict[str, Sent] = {}
    for s in list(seen):
        if (s.ay or s.bx) and s.unit not in first:
            first[s.unit] = s
    return first if set(first) >= set(units) else None


def in_one_turn(first: dict[str, Sent]) -> bool:
    """The robot's drives got their speeds in one turn of the schedule: at the same
    scheduled moment (a robot's units share one phase; the next robot's is a whole
    phase away, 10 ms at 50 Hz with two). A drive whose reply to the previous command
    comes in after its turn is due waits for it (one exchange in flight per drive), so
    its frame may leave a poll later, within the same turn: 5 ms allows for that."""
    times = [s.t for s in first.values()]
    return max(times) - min(times) < 0.005
