"""Judgements from sample series, pure: what a jog says of the wiring, what a step says of
the tuning, what the e-stop rehearsal measured. No clock, no bus: a list of samples in,
:class:`~.model.Check` records out, so every rule is tested on numbers alone."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

from abh3_supervisor.commission.model import AXES, Check, Settings, Trace, Verdict

Samples = Sequence[tuple[float, float, float]]  # (t, A, B)

# the guard's and the jog's thresholds, as fractions of the asked speed
FOLLOWS = 0.2  # below this the motor is taken as not moving
OTHER_MOVES = 0.3  # the motor not asked moving this much: a wiring fault
OVERSPEED = 2.0  # beyond 2× the asked speed: stop at once
# no DP0 answer for this long while a unit is jogged: communication lost, stop it (the
# bound held on the wire is 0.25 s after the last answer; the rest is the loop's margin)
SILENCE_S = 0.2
SIZE_TOLERANCE = 0.15  # a settled feedback within ±15 % of the command is the right size
STALL_CURRENT = 30.0  # % above the idle current: the drive is pushing a motor that does not turn
SETTLE_BAND = 0.05  # settling: within ±5 % of the step


def polarity_fix(axis: int) -> str:
    name = AXES[axis]
    return (
        f"motor {name}'s encoder (or motor phase) wiring is backwards: swap it at the drive, "
        f"or invert axis {name}'s polarity in the drive's system parameters (0x4000–0x4083, "
        "'polarity' in the maker's tool); the YAML cannot correct a feedback sign"
    )


SWAP_FIX = (
    "motors A and B are swapped at the drive: exchange their motor and encoder cables "
    "(A is the left wheel, B the right, as the velocity model and odometry assume)"
)
MODEL_FIX = "velocity_model in the YAML must be the drive's model (`abh3 scan` reads it)"
COMMUNICATION_FIX = (
    "the drive stopped answering on CAN: check the CAN cable and its connectors, the "
    "termination (120 Ω at both ends of the bus), the drive's control power, and its CAN "
    "settings against the file (node address, bit rate, host id: `abh3 verify`, "
    "`abh3 scan`); `abh3 status` shows the bus's errors"
)


def encoder_fix(axis: int) -> str:
    name = AXES[axis]
    return (
        f"motor {name}'s encoder/resolver cable (connector, supply) and the drive's sensor "
        f"setting of axis {name} (0x{0x0002 + 0x2000 * axis:04X}–0x{0x001D + 0x2000 * axis:04X})"
    )


def signed_peak(values: Sequence[float]) -> float:
    """The value of largest magnitude, with its sign (0 for none)."""
    return max(values, key=abs, default=0.0)


def window(samples: Samples, start: float, end: float) -> list[tuple[float, float, float]]:
    return [s for s in samples if start <= s[0] <= end]


@dataclass(frozen=True, slots=True)
class Phase:
    """One constant command of a jog: motor ``axis`` asked for ``speed`` from ``start``
    to ``end`` (trace time); ``complete``: it ran its whole length (the guard let it)."""

    axis: int
    speed: float
    start: float
    end: float
    complete: bool = True


def response(samples: Samples, phase: Phase) -> tuple[float, float]:
    """(asked motor, other motor) feedback of a phase: the mean over its last 40 % when it
    ran its length, else the signed peak up to the stop (an early stop has no steady part)."""
    k, o = 1 + phase.axis, 2 - phase.axis
    if phase.complete:
        tail = window(samples, phase.end - 0.4 * (phase.end - phase.start), phase.end)
        if tail:
            return sum(s[k] for s in tail) / len(tail), sum(s[o] for s in tail) / len(tail)
    inside = window(samples, phase.start, phase.end + 0.05)
    return signed_peak([s[k] for s in inside]), signed_peak([s[o] for s in inside])


def judge_direction(trace: Trace, phases: Sequence[Phase]) -> list[Check]:
    """Direction, size and which motor moved, for each phase of a jog (forward, back)."""
    checks: list[Check] = []
    step = trace.title
    for phase in phases:
        v = phase.speed
        asked, other = response(trace.feedback, phase)
        name = AXES[phase.axis]
        other_name = AXES[1 - phase.axis]
        where = f"{'+' if v > 0 else '−'}{abs(v):g} min⁻¹"
        measured = f"{name} {asked:+.1f}, {other_name} {other:+.1f} min⁻¹"
        limit = f"{name} {v:+g} ±{SIZE_TOLERANCE:.0%}, {other_name} ~0"
        if abs(other) > OTHER_MOVES * abs(v) and abs(asked) < FOLLOWS * abs(v):
            checks.append(
                Check(step, f"swapped axes ({where})", Verdict.FAIL, measured, limit, SWAP_FIX)
            )
        elif abs(other) > OTHER_MOVES * abs(v) and abs(asked) < (1 - SIZE_TOLERANCE) * abs(v):
            checks.append(
                Check(
                    step,
                    f"wrong velocity_model ({where})",
                    Verdict.FAIL,
                    measured,
                    limit,
                    MODEL_FIX,
                )
            )
        elif abs(asked) < FOLLOWS * abs(v):
            checks.append(no_motion(trace, phase, measured, limit))
        elif asked * v < 0:
            checks.append(
                Check(
                    step,
                    f"reversed axis {name} ({where})",
                    Verdict.FAIL,
                    measured,
                    limit,
                    polarity_fix(phase.axis),
                )
            )
        elif abs(asked / v - 1) > SIZE_TOLERANCE:
            checks.append(
                Check(
                    step,
                    f"feedback size ({where})",
                    Verdict.FAIL,
                    f"{measured} (×{asked / v:.2f})",
                    limit,
                    f"{MODEL_FIX}; the drive's speed scaling of axis {name} "
                    f"(0x{0x0002 + 0x2000 * phase.axis:04X}–)",
                )
            )
        else:
            checks.append(
                Check(step, f"direction and size ({where})", Verdict.PASS, measured, limit)
            )
        if checks[-1].verdict is not Verdict.PASS:
            break  # the first wrong answer names the fault; the rest only repeats it
    return checks


def communication_lost(step: str, measured: str) -> Check:
    """The drive fell silent while moving: the guard stopped it; nothing of the motor can
    be judged from answers that did not come."""
    return Check(
        step,
        "communication lost",
        Verdict.FAIL,
        measured,
        f"an answer to every command (within {SILENCE_S:g} s)",
        COMMUNICATION_FIX,
    )


def no_motion(trace: Trace, phase: Phase, measured: str, limit: str) -> Check:
    """The asked motor reports nothing: no encoder if the drive pushes current into it."""
    k = 1 + phase.axis
    name = AXES[phase.axis]
    before = [s[k] for s in trace.current if s[0] < phase.start]
    idle = abs(before[-1]) if before else 0.0
    during = [abs(s[k]) for s in window(trace.current, phase.start, phase.end + 0.05)]
    peak = max(during, default=0.0)
    moved = _pulses_moved(trace, phase)
    if peak > idle + STALL_CURRENT and not moved:
        return Check(
            trace.title,
            f"no encoder on motor {name}",
            Verdict.FAIL,
            f"{measured}; no pulses; current {idle:.0f} → {peak:.0f} %",
            limit,
            encoder_fix(phase.axis),
        )
    return Check(
        trace.title,
        f"no feedback from motor {name}",
        Verdict.FAIL,
        f"{measured}; current {peak:.0f} %",
        limit,
        f"motor {name} neither turns nor draws current: the drive's power stage (main supply), "
        f"the motor cable, the brake (BRAKE_FAULT), and that START reaches axis {name}",
    )


def _pulses_moved(trace: Trace, phase: Phase) -> bool:
    k = 1 + phase.axis
    counts = [s[k] for s in trace.pulses if phase.start - 0.2 <= s[0] <= phase.end + 0.2]
    return len(counts) >= 2 and max(counts) != min(counts)


def integral(samples: Samples, index: int, start: float, end: float) -> float:
    """∫ samples[index] dt from ``start`` to ``end`` (trapezoids, linear between samples,
    held flat outside them)."""
    points = [(s[0], s[index]) for s in samples]
    if not points or end <= start:
        return 0.0

    def at(t: float) -> float:
        if t <= points[0][0]:
            return points[0][1]
        for (t0, v0), (t1, v1) in itertools.pairwise(points):
            if t0 <= t <= t1:
                return v0 if t1 == t0 else v0 + (v1 - v0) * (t - t0) / (t1 - t0)
        return points[-1][1]

    inner = [(t, v) for t, v in points if start < t < end]
    path = [(start, at(start)), *inner, (end, at(end))]
    return sum((t1 - t0) * (v0 + v1) / 2 for (t0, v0), (t1, v1) in itertools.pairwise(path))


def measured_pulses_per_rev(trace: Trace, axis: int) -> float | None:
    """Pulses per motor revolution, from the pulse counts (broadcast 4) against the
    revolutions the DP0 feedback integrates to between the two counts that saw the most
    motion; None without two counts around a turn of at least a tenth of a revolution."""
    k = 1 + axis
    best: tuple[float, float] | None = None
    first = trace.pulses[0] if trace.pulses else None
    for later in trace.pulses[1:]:
        assert first is not None
        revs = integral(trace.feedback, k, first[0], later[0]) / 60
        if abs(revs) >= 0.1 and (best is None or abs(revs) > abs(best[1])):
            best = (later[k] - first[k], revs)
    if best is None:
        return None
    return best[0] / best[1]


# where the file sets a motor's pulses per revolution (its name; set to a value: "{}"
# the value) and its gear ratio: here a unit's geometry, else its robot's wheel
GEOMETRY_KEYS = (
    "geometry.pulses_per_rev",
    "geometry.pulses_per_rev: {}",
    "the gear ratio geometry.rate_num/rate_den",
)


def judge_scale(
    trace: Trace,
    axis: int,
    yaml_ppr: float,
    settings: Settings,
    keys: tuple[str, str, str] = GEOMETRY_KEYS,
) -> Check:
    """``keys``: where the file sets the pulses per revolution and the gear ratio of this
    motor (a unit's geometry, or its robot's wheel)."""
    name = AXES[axis]
    ppr_key, ppr_set, gear_key = keys
    if yaml_ppr <= 0:
        return Check(
            trace.title,
            f"gear/geometry scale of motor {name}",
            Verdict.WARN,
            "not checked",
            f"{ppr_key} in the YAML",
            f"give {ppr_key} (the encoder's pulses per motor revolution) to check "
            "the gear and geometry against the pulse counts",
        )
    measured = measured_pulses_per_rev(trace, axis)
    limit = f"{yaml_ppr:g} ±{settings.scale_tolerance:.0%} pulses/rev"
    if measured is None:
        return Check(
            trace.title,
            f"gear/geometry scale of motor {name}",
            Verdict.WARN,
            "too few pulse counts (broadcast 4) during the jog",
            limit,
            "broadcast.mask must include packet 4 (pulse counts)",
        )
    ratio = measured / yaml_ppr
    text = f"{measured:.0f} pulses/rev (×{ratio:.3f})"
    if abs(ratio - 1) <= settings.scale_tolerance:
        return Check(trace.title, f"gear/geometry scale of motor {name}", Verdict.PASS, text, limit)
    return Check(
        trace.title,
        f"gear/geometry scale of motor {name} off by {ratio - 1:+.0%}",
        Verdict.FAIL,
        text,
        limit,
        f"{ppr_set.format(f'{measured:.0f}')} if the encoder is right (YAML {yaml_ppr:g}); "
        f"else {gear_key} or the drive's sensor setting of axis "
        f"{name} (0x{0x0002 + 0x2000 * axis:04X}–0x{0x001D + 0x2000 * axis:04X})",
    )


def judge_pair(
    step: str,
    a: float | None,
    b: float | None,
    settings: Settings,
    ppr_key: str = GEOMETRY_KEYS[0],
) -> Check:
    """Without ``geometry.pulses_per_rev`` the two motors are held against each other: a
    robot's wheels share a motor, gear and encoder type, so they count alike. Agreeing is
    a pass (the file asks no more); the measured text says the YAML could give the key."""
    name = "gear/geometry scale of motors A and B"
    fix = (
        f"give {ppr_key} (the encoder's pulses per motor revolution) to check "
        "the gear and geometry against the YAML"
    )
    if a is None or b is None or not a:
        return Check(step, name, Verdict.WARN, "not checked", ppr_key, fix)
    ratio = b / a
    measured = f"A {a:.0f}, B {b:.0f} pulses/rev (B ×{ratio:.3f} of A)"
    limit = f"A = B ±{settings.scale_tolerance:.0%} (no {ppr_key})"
    if abs(ratio - 1) <= settings.scale_tolerance:
        note = f"; {ppr_key} in the YAML would check them against the encoder"
        return Check(step, name, Verdict.PASS, measured + note, limit)
    return Check(
        step,
        f"gear/geometry scale: motor B counts {ratio - 1:+.0%} against motor A",
        Verdict.FAIL,
        measured,
        limit,
        "one motor's encoder, gear or sensor setting differs from the other's (axis A "
        f"0x0002–0x001D, B 0x2002–0x201D); then give {ppr_key}",
    )


# ---------------------------------------------------------------- step response


@dataclass(frozen=True, slots=True)
class StepMetrics:
    rise_s: float | None  # 10 % → 90 %
    overshoot: float  # fraction of the step
    settling_s: float | None  # last entry into ±5 %, from the step
    steady_error: float  # fraction, over the hold's last 20 %
    peak_current: float  # %, the moved motor, broadcast 3


def _crossing(samples: list[tuple[float, float]], level: float) -> float | None:
    for (t0, v0), (t1, v1) in itertools.pairwise(samples):
        if v0 < level <= v1:
            return t0 + (t1 - t0) * (level - v0) / (v1 - v0)
    return None


def step_metrics(trace: Trace, axis: int, speed: float, start: float, end: float) -> StepMetrics:
    """The step from 0 to ``speed`` on ``axis`` commanded at ``start`` and held to ``end``."""
    k = 1 + axis
    sign = math.copysign(1.0, speed)
    size = abs(speed)
    pts = [(t, sign * s[k]) for s in trace.feedback if start <= (t := s[0]) <= end]
    pts = [(start, 0.0), *pts] if not pts or pts[0][0] > start else pts
    t10, t90 = _crossing(pts, 0.1 * size), _crossing(pts, 0.9 * size)
    rise = t90 - t10 if t10 is not None and t90 is not None else None
    peak = max((v for _, v in pts), default=0.0)
    overshoot = max(0.0, (peak - size) / size)
    outside = [t for t, v in pts if abs(v - size) > SETTLE_BAND * size]
    after = [t for t, _ in pts if outside and t > outside[-1]]
    settling = (after[0] - start) if after else None
    tail = [v for t, v in pts if t >= end - 0.2 * (end - start)]
    steady = abs(sum(tail) / len(tail) - size) / size if tail else 1.0
    currents = [abs(s[k]) for s in trace.current if start <= s[0] <= end]
    return StepMetrics(rise, overshoot, settling, steady, max(currents, default=0.0))


def judge_step(trace: Trace, m: StepMetrics, settings: Settings, axis: int) -> list[Check]:
    name = AXES[axis]
    tuning = (
        f"the drive's tuning of the selected data set: accel 0x5020/decel 0x5040 (A/Y), "
        f"gains KP 0x5060 / KI 0x5070; limits.velocity for motor {name}"
    )

    def row(label: str, ok: bool | None, measured: str, limit: str) -> Check:
        verdict = Verdict.WARN if ok is None else (Verdict.PASS if ok else Verdict.WARN)
        return Check(trace.title, label, verdict, measured, limit, "" if ok else tuning)

    def ms(s: float | None) -> str:
        return "never" if s is None else f"{s * 1000:.0f} ms"

    return [
        row(
            "rise time 10–90 %",
            m.rise_s is not None and m.rise_s <= settings.rise_max_s,
            ms(m.rise_s),
            f"≤ {settings.rise_max_s * 1000:.0f} ms",
        ),
        row(
            "overshoot",
            m.overshoot <= settings.overshoot_max,
            f"{m.overshoot:.1%}",
            f"≤ {settings.overshoot_max:.0%}",
        ),
        row(
            f"settling time (±{SETTLE_BAND:.0%})",
            m.settling_s is not None and m.settling_s <= settings.settling_max_s,
            ms(m.settling_s),
            f"≤ {settings.settling_max_s * 1000:.0f} ms",
        ),
        row(
            "steady-state error",
            m.steady_error <= settings.steady_error_max,
            f"{m.steady_error:.1%}",
            f"≤ {settings.steady_error_max:.0%}",
        ),
        row(
            "peak current",
            m.peak_current <= settings.current_max,
            f"{m.peak_current:.0f} %",
            f"≤ {settings.current_max:.0f} %",
        ),
    ]


# ---------------------------------------------------------------- e-stop


def judge_estop(latency: float | None, period: float) -> Check:
    limit = f"≤ {period * 1000:.0f} ms (one command period)"
    if latency is None:
        return Check(
            "e-stop",
            "key → first stop frame",
            Verdict.FAIL,
            "no stop frame seen",
            limit,
            "the unit must be commanded (role: command) and online",
        )
    ok = latency <= period
    return Check(
        "e-stop",
        "key → first stop frame",
        Verdict.PASS if ok else Verdict.FAIL,
        f"{latency * 1000:.1f} ms",
        limit,
        ""
        if ok
        else "command_rate_hz is the e-stop's latency: raise it (`abh3 check` shows the "
        "bus load), or a host too loaded to keep its command period",
    )
