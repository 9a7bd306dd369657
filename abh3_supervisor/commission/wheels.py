"""What the robot step's observations say of how the robot is built, pure: which wheel
each (unit, axis) turned and which way it rolled the robot in, named faults with their
fixes out. No clock, no bus: tested on observations alone.

A wheel's *place* is named as the file names it: the (unit, axis) the file gives the wheel
there. The operator knows places by where they are: side, and front to rear in the order
the file lists a side's wheels (:func:`places`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from abh3_supervisor.commission.model import AXES, Check, Verdict
from abh3_supervisor.core.robot import RobotConfig, Side, Wheel

STEP = "robot"
Place = tuple[str, int]  # (unit, axis) of the wheel the file puts there
GEOMETRY_TOLERANCE = 0.05  # a measured track or diameter beyond ±5 % of the file's: a fail


@dataclass(frozen=True, slots=True)
class Seen:
    """What one wheel's jog did: the place of the wheel that turned (None: none did) and
    which way it rolled the robot (+1 forward, −1 backward, 0 not at all)."""

    place: Place | None
    direction: int
    # the commanded motor's fastest by its drive's own feedback [min⁻¹] when it turned (at
    # least half the speed asked); None: it did not, or nobody watched
    motor_min: float | None = None


def places(robot: RobotConfig) -> dict[Place, str]:
    """Each wheel's place, by name: ``left``/``right`` for one wheel a side,
    ``front-left``/``rear-left`` for two (the file lists a side front to rear), ``left 1``,
    ``left 2``… for more."""
    out: dict[Place, str] = {}
    for side in (Side.LEFT, Side.RIGHT):
        of_side = [w for w in robot.wheels if w.side is side]
        for i, w in enumerate(of_side):
            if len(of_side) == 1:
                name = side.value
            elif len(of_side) == 2:
                name = f"{('front', 'rear')[i]}-{side.value}"
            else:
                name = f"{side.value} {i + 1}"
            out[w.unit, w.axis] = name
    return out


def elsewhere(robot: RobotConfig, others: Sequence[RobotConfig]) -> dict[Place, str]:
    """The other robots' wheel places, by name ("left of robot rear")."""
    return {
        place: f"{name} of robot {other.name}"
        for other in others
        if other.name != robot.name
        for place, name in places(other).items()
    }


def _where(robot: RobotConfig) -> str:
    return "a robots: section" if robot.implicit else f"robots: {robot.name}"


def _wheel_key(robot: RobotConfig, w: Wheel) -> str:
    if robot.implicit:
        return f"units.{w.unit}.geometry (axis {AXES[w.axis]})"
    index = robot.wheels.index(w)
    return f"robots.{robot.name}.wheels[{index}] ({w.unit} axis {AXES[w.axis]})"


def mirrored_fix(robot: RobotConfig, w: Wheel) -> str:
    if robot.implicit:
        yaml = (
            f"describe the robot in {_where(robot)} with sign: {-w.sign} for unit {w.unit} "
            f"axis {AXES[w.axis]} (docs/robots.md)"
        )
    else:
        yaml = f"sign: {-w.sign} for {_wheel_key(robot, w)} (it is {w.sign})"
    return (
        f"{yaml}, or invert axis {AXES[w.axis]}'s direction in the drive (its polarity, "
        "0x4000–0x4083, reversing motor and encoder together)"
    )


def swapped_drives_fix(robot: RobotConfig, u: str, v: str, other: RobotConfig | None) -> str:
    """``other``: the robot ``v`` drives when it is not ``robot`` (a swap between robots)."""
    if robot.implicit and (other is None or other.implicit):
        yaml = f"swap the abh3_id of units {u} and {v} in the YAML"
    elif other is None or other.name == robot.name:
        yaml = (
            f"in robots.{robot.name}.wheels swap unit: {u} and unit: {v} (or swap the two "
            "units' abh3_id)"
        )
    else:  # one unit, one robot: a wheel list alone cannot take the other robot's unit
        yaml = (
            f"swap the abh3_id of units {u} and {v} in the YAML (or, in both robots' wheels, "
            f"unit: {u} → {v} in {_wheels_of(robot)} and unit: {v} → {u} in {_wheels_of(other)})"
        )
    return f"{yaml}, or swap the two drives' motor cables (with their encoders)"


def _wheels_of(robot: RobotConfig) -> str:
    return f"units.{robot.name}.geometry" if robot.implicit else f"robots.{robot.name}.wheels"


def swapped_axes_fix(robot: RobotConfig, unit: str) -> str:
    if robot.implicit:
        yaml = (
            f"describe the robot in a robots: section with unit {unit}'s axis A on the "
            "right and B on the left (docs/robots.md)"
        )
    else:
        yaml = f"swap axis: A and axis: B of unit {unit}'s wheels in robots.{robot.name}.wheels"
    return f"{yaml}, or swap motor A's and B's cables together with their encoder cables"


def _swapped_with(
    robot: RobotConfig, seen: dict[Place, Seen], u: str, has: Callable[[Place], bool]
) -> str | None:
    """The unit whose wheels (axis for axis) ``u``'s wheels turned, if another: each
    turned that unit's wheel on its own axis, or nothing where that unit has no wheel
    on it (``has``: is there a wheel at a place, of this robot or another)."""
    mine = [w for w in robot.wheels if w.unit == u]
    turned = [seen[w.unit, w.axis].place for w in mine]
    others = {p[0] for p in turned if p is not None}
    if len(others) != 1 or u in others:
        return None
    v = others.pop()
    for w, p in zip(mine, turned, strict=True):
        if p != (v, w.axis) and not (p is None and not has((v, w.axis))):
            return None
    return v


def judge_wheels(
    robot: RobotConfig, seen: dict[Place, Seen], others: Sequence[RobotConfig] = ()
) -> list[Check]:
    """One check per wheel (a pass where it is as the file says) and one per fault found:
    drives swapped, A and B swapped with their encoders, a mirrored mounting.
    ``others``: the other robots whose wheels a wheel may have turned (a unit's drive on
    another robot's wheels: the two drives swapped)."""
    names = {**elsewhere(robot, others), **places(robot)}
    robot_of = {u: o for o in others if o.name != robot.name for u in o.units}
    signs = {(w.unit, w.axis): w.sign for r in (*others, robot) for w in r.wheels}
    checks: list[Check] = []
    explained: set[Place] = set()
    units = robot.units

    def has(place: Place) -> bool:
        return place in names

    for u in units:
        v = _swapped_with(robot, seen, u, has)
        if v is None or (
            v in units
            and (_swapped_with(robot, seen, v, has) != u or units.index(v) < units.index(u))
        ):
            continue  # not swapped, or named from the other unit's side
        pairs = [(w, seen[w.unit, w.axis]) for w in robot.wheels if w.unit in (u, v)]
        turned = ", ".join(
            f"{w.name} turned {names[s.place]}"
            if s.place is not None
            else f"{w.name} turned none ({u if w.unit == v else v} has no wheel on axis "
            f"{AXES[w.axis]})"
            for w, s in pairs
        )
        first, second = sorted((u, v), key=_order(units))
        checks.append(
            Check(
                STEP,
                f"drives swapped: {first} ↔ {second}",
                Verdict.FAIL,
                turned,
                "each unit turns its own wheels",
                swapped_drives_fix(robot, first, second, robot_of.get(v))
                + "; then commission again: a fault behind the swap shows once it is fixed",
            )
        )
        # a wheel that rolled the other way than its own mounting and the commanded
        # wheel's make it: mirrored besides (the wheel at its place)
        for w, s in pairs:
            if s.place is not None and s.direction and s.direction != w.sign * signs[s.place]:
                checks.append(
                    Check(
                        STEP,
                        f"mirrored wheel at {names[s.place]} (besides the swap)",
                        Verdict.FAIL,
                        f"turned by {w.name}, it rolled the robot backwards when asked forwards",
                        "forward",
                        "once the drives are swapped back, commission again: the sign: of "
                        f"the {names[s.place]} wheel, or its axis's direction in the drive",
                    )
                )
        explained |= {(w.unit, w.axis) for w, _ in pairs}
    for u in units:
        a, b = robot.wheel(u, 0), robot.wheel(u, 1)
        if a is None or b is None or {(u, 0), (u, 1)} & explained:
            continue
        if seen[u, 0].place == (u, 1) and seen[u, 1].place == (u, 0):
            checks.append(
                Check(
                    STEP,
                    f"A and B swapped with their encoders: {u}",
                    Verdict.FAIL,
                    f"{a.name} turned {names[u, 1]}, {b.name} turned {names[u, 0]}",
                    "each axis turns its own wheel",
                    swapped_axes_fix(robot, u),
                )
            )
            explained |= {(u, 0), (u, 1)}
    for w in robot.wheels:
        place = (w.unit, w.axis)
        s = seen[place]
        label = f"wheel {w.name} ({names[place]})"
        if place in explained:
            continue
        if s.place is None or s.direction == 0:
            checks.append(_still(robot, w, s, names[place]))
        elif s.place != place:
            checks.append(
                Check(
                    STEP,
                    f"{label} turned another wheel",
                    Verdict.FAIL,
                    f"{names[s.place]} turned",
                    f"{names[place]}",
                    f"the unit: and axis: of the {names[s.place]} wheel in {_where(robot)} "
                    f"are {w.unit} and {AXES[w.axis]}, or the motor cables are crossed",
                )
            )
        elif s.direction < 0:
            checks.append(
                Check(
                    STEP,
                    f"mirrored wheel {w.name} ({names[place]})",
                    Verdict.FAIL,
                    "it rolled the robot backwards when asked forwards",
                    "forward",
                    mirrored_fix(robot, w),
                )
            )
        else:
            checks.append(Check(STEP, label, Verdict.PASS, "turned, rolling the robot forward"))
    return checks


def _still(robot: RobotConfig, w: Wheel, s: Seen, place: str) -> Check:
    """A wheel that did not turn. Its drive's feedback may say its motor turned: then
    the motor is not on that wheel — when the drive's other axis is no wheel of the
    robot, A and B swapped with their encoders (the other motor is on this wheel, and
    this one on nothing), or the wheel decoupled."""
    label = f"wheel {w.name} ({place})"
    turning = s.motor_min is not None
    if not turning or robot.wheel(w.unit, 1 - w.axis) is not None:
        spun = f" although drive {w.unit} reports motor {AXES[w.axis]} turning" if turning else ""
        return Check(
            STEP,
            f"{label} did not turn",
            Verdict.FAIL,
            f"no wheel turned{spun}",
            f"{place} forward",
            "is the wheel coupled (gearbox, brake) and free? the drive's other "
            f"checks passed; the wheel's unit: and axis: in {_where(robot)}",
        )
    other = AXES[1 - w.axis]
    return Check(
        STEP,
        f"A and B swapped with their encoders: {w.unit} ({label} did not turn)",
        Verdict.FAIL,
        f"no wheel turned although drive {w.unit} reports motor {AXES[w.axis]} turning "
        f"({s.motor_min:+.0f} min⁻¹); its axis {other} is no wheel of the robot, so its "
        f"motor {other} is likely the one on this wheel",
        f"{place} forward",
        f"axis: {other} for {_wheel_key(robot, w)}, or swap motor A's and B's cables "
        "together with their encoder cables; else the wheel is not coupled to its motor "
        "(gearbox, key, brake)"
        + "".join(
            f"; or the drives of {w.unit} and {v} swapped, if {v}'s wheel stood still too "
            "(their abh3_id, or the cables)"
            for v in robot.units
            if v != w.unit and robot.wheel(v, w.axis) is None
        ),
    )


def _order(units: tuple[str, ...]) -> Callable[[str], int]:
    """The robot's units first, in its order; another robot's after."""
    return lambda u: units.index(u) if u in units else len(units)


def judge_diameter(robot: RobotConfig, expected_m: float, measured_m: float) -> Check:
    """A straight run: the distance the encoders and the file's diameters give against the
    one measured. Their ratio is the diameters' (every wheel alike)."""
    ratio = measured_m / expected_m if expected_m else math.nan
    diameter = robot.wheels[0].diameter_m
    measured = f"ran {measured_m:.3f} m measured, {expected_m:.3f} m by the file's wheels"
    if not math.isfinite(ratio) or abs(ratio - 1) <= GEOMETRY_TOLERANCE:
        verdict = Verdict.PASS if math.isfinite(ratio) else Verdict.FAIL
        return Check(STEP, "wheel diameter (straight run)", verdict, measured, "±5 %")
    key = (
        f"units.{robot.name}.geometry.wheel: {diameter * ratio:.4g}"
        if robot.implicit
        else f"diameter_m: {diameter * ratio:.4g} in robots: {robot.name} (it is {diameter:g})"
    )
    return Check(
        STEP,
        f"wheel diameter off by {100 * (ratio - 1):+.0f}%",
        Verdict.FAIL,
        measured,
        "±5 %",
        f"{key}; a diameter, not a radius — or a gear_ratio that is not the motor's revs "
        "per wheel rev",
    )


def judge_sides(
    robot: RobotConfig,
    expected: tuple[float, float],
    measured_m: float,
    drift_rad: float,
) -> Check | None:
    """A straight run that curved: each side's true travel from the distance and the
    heading it turned by (the file's track), against what its encoders and diameters
    give (``expected``: left, right). None when both sides agree within the tolerance
    (the diameters, if off, are off alike: :func:`judge_diameter`)."""
    half = drift_rad * robot.track_m / 2
    true = (measured_m - half, measured_m + half)
    ratios = [t / e if e else math.nan for t, e in zip(true, expected, strict=True)]
    if not all(map(math.isfinite, ratios)) or abs(ratios[0] - ratios[1]) <= GEOMETRY_TOLERANCE:
        return None
    both = list(zip((Side.LEFT, Side.RIGHT), ratios, strict=True))
    off = [(side, r) for side, r in both if abs(r - 1) > GEOMETRY_TOLERANCE] or [
        max(both, key=lambda s: abs(s[1] - 1))
    ]
    named = " and ".join(
        f"{side.value} side ({', '.join(_units_of(robot, side))}) {100 * (ratio - 1):+.0f}%"
        for side, ratio in off
    )
    fixes = [
        _diameter_fix(robot, w, ratio)
        for side, ratio in off
        for w in robot.wheels
        if w.side is side
    ]
    return Check(
        STEP,
        f"wheel diameter off: {named}",
        Verdict.FAIL,
        f"the straight run curved {math.degrees(drift_rad):+.1f}°: left side rolled "
        f"{true[0]:.3f} m, right {true[1]:.3f} m; the file's wheels say {expected[0]:.3f} m, "
        f"{expected[1]:.3f} m",
        "±5 %, both sides alike",
        "; ".join(fixes) + " — a diameter, not a radius; or a gear_ratio that is not the "
        "motor's revs per wheel rev",
    )


def _units_of(robot: RobotConfig, side: Side) -> list[str]:
    return list(dict.fromkeys(w.unit for w in robot.wheels if w.side is side))


def _diameter_fix(robot: RobotConfig, w: Wheel, ratio: float) -> str:
    value = f"diameter_m: {w.diameter_m * ratio:.4g}"
    if robot.implicit:
        return (
            f"describe the robot in a robots: section with {value} for unit {w.unit} axis "
            f"{AXES[w.axis]} (units.{w.unit}.geometry.wheel is both wheels'; docs/robots.md)"
        )
    return f"{value} for {_wheel_key(robot, w)} (it is {w.diameter_m:g})"


def judge_track(robot: RobotConfig, expected_rad: float, measured_rad: float) -> Check:
    """A turn on the spot: the angle the encoders and the file's track give against the
    one measured; the true track is the file's × expected / measured."""
    measured = (
        f"{math.degrees(measured_rad):.1f}° measured, "
        f"{math.degrees(expected_rad):.1f}° by the file's track"
    )
    if not measured_rad:
        return Check(STEP, "track (turn on the spot)", Verdict.FAIL, measured, "±5 %")
    ratio = expected_rad / measured_rad
    if abs(ratio - 1) <= GEOMETRY_TOLERANCE:
        return Check(STEP, "track (turn on the spot)", Verdict.PASS, measured, "±5 %")
    track = robot.track_m * ratio
    key = (
        f"units.{robot.name}.geometry.width: {track:.4g}"
        if robot.implicit
        else f"track_m: {track:.4g} in robots: {robot.name} (it is {robot.track_m:g})"
    )
    return Check(
        STEP,
        f"track off by {100 * (ratio - 1):+.0f}%",
        Verdict.FAIL,
        measured,
        "±5 %",
        f"{key}: the distance between the left and right wheels' contact lines",
    )
