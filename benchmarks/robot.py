"""9. A robot's twist, decided once for all its drives: its cost on the loop.

A streamed twist (a joystick, ``cmd_vel``) is submitted to the arbitration and becomes
every wheel's speed in one plan (core/robot_motion.py). The figure: loop time per twist
submission, from ``InputArbiter.submit`` to both units' frames set, for a four-wheel
skid-steer on two drives (with limits and an acceleration ramp) — beside the baseline of
the same twist to two independent one-drive robots (what the supervisor did before
robots existed: each unit converted the twist on its own). No bus, no I/O: a fake clock.

Run alone: ``python -m benchmarks.robot [--count N] [--runs N]``.
"""

from __future__ import annotations

import argparse
import math
import time

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.inputs import InputSource, Twist
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.plugin_host.feed import InputFeed
from benchmarks.report import Row, machine, median_of, print_rows

UNITS = """
buses:
  b: {interface: virtual, channel: bench-robot, simulate: true}
units:
  - {name: l, abh3_id: 1, velocity_model: motor}
  - {name: r, abh3_id: 3, velocity_model: motor}
"""
SKID = """
robots:
  - name: skid
    track_m: 0.6
    diameter_m: 0.25
    gear_ratio: 20
    limits: {linear_mps: 1.2, angular_radps: 1.5, linear_accel_mps2: 0.8}
    wheels:
      - {unit: l, axis: A, side: left}
      - {unit: l, axis: B, side: left}
      - {unit: r, axis: A, side: right, sign: -1}
      - {unit: r, axis: B, side: right, sign: -1}
"""


class _Stream(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


def per_twist_us(text: str, count: int) -> float:
    """Microseconds of loop time per streamed twist submission."""
    now = [0.0]
    sup = Supervisor(parse_config(text, "bench.yaml"), clock=lambda: now[0])
    for unit in ("l", "r"):
        sup.apply_text(unit, "SERVO ON ON")
        sup.apply_text(unit, "START ON ON")
    sup.arbiter.add(_Stream("joy", ("l", "r"), timeout=math.inf))
    twists = [Twist(0.5 + 0.001 * (i % 100), 0.2) for i in range(count)]
    started = time.perf_counter()
    for i, twist in enumerate(twists):
        now[0] = i * 0.02  # a 50 Hz stream
        sup.arbiter.submit("joy", twist, now[0])
    return (time.perf_counter() - started) / count * 1e6


def rows(count: int, runs: int) -> list[Row]:
    section = "9. a robot's twist per submission (fake clock, no I/O)"
    robot = median_of(runs, lambda: per_twist_us(UNITS + SKID, count))
    alone = median_of(runs, lambda: per_twist_us(UNITS, count))
    return [
        Row(
            section,
            "skid-steer on 2 drives, limits + ramp",
            robot,
            alone,
            "µs",
            "<=3x",
            robot <= 3 * alone,
        ),
    ]


def main() -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.robot", description=__doc__)
    p.add_argument("--count", type=int, default=20_000)
    p.add_argument("--runs", type=int, default=3)
    a = p.parse_args()
    print(f"machine: {machine()}")
    print_rows(rows(a.count, a.runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
