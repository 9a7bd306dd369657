"""The ``robots:`` section: robots made of wheels on any units' axes (docs/robots.md)."""

from __future__ import annotations

from typing import Any

from abh3_supervisor.config.model import Role, UnitConfig
from abh3_supervisor.config.source import Path, Section, Source
from abh3_supervisor.core.robot import AXES, RobotConfig, RobotLimits, Side, Wheel

ROBOT_KEYS = {
    "name",
    "track_m",
    "wheels",
    "limits",
    "frame_id",
    "child_frame_id",
    # defaults for the robot's wheels
    "diameter_m",
    "gear_ratio",
    "pulses_per_rev",
}
WHEEL_KEYS = {"unit", "axis", "side", "sign", "diameter_m", "gear_ratio", "pulses_per_rev"}
ROBOT_LIMIT_KEYS = {"linear_mps", "angular_radps", "linear_accel_mps2", "angular_accel_radps2"}
# keys a user reaching for a radius writes: never read, always pointed at the diameter
RADIUS_KEYS = {"radius", "radius_m", "wheel_radius", "wheel_radius_m"}
DIAMETER_MAX_M = 10.0
FRAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_/")


# keys users reach for, pointed at ours (difflib finds no match for these)
SYNONYMS = {
    "gear": "gear_ratio",
    "ratio": "gear_ratio",
    "reduction": "gear_ratio",
    "diameter": "diameter_m",
    "wheel": "diameter_m",
    "track": "track_m",
    "width": "track_m",
    "wheelbase": "track_m",
    "direction": "sign",
    "mirrored": "sign",
    "invert": "sign",
}


def section(src: Source, path: Path, data: Any, allowed: set[str], diameter: str) -> Section:
    """A mapping checked against ``allowed``: a radius-like key points at ``diameter``, a
    synonym at our key, each said once; the rest as every section's unknown keys."""
    checked = Section(src, path, data, None)
    radius_keys(checked, diameter)
    said = set(RADIUS_KEYS)
    for key in set(checked.data) & set(SYNONYMS) - allowed:
        if SYNONYMS[key] in allowed:
            checked.error(key, f"unknown key; did you mean '{SYNONYMS[key]}'?")
            said.add(key)
    checked.only(allowed, said)
    return checked


def radius_keys(section: Section, diameter: str) -> None:
    """Point every radius-like key of ``section`` at the diameter key ``diameter``."""
    for key in RADIUS_KEYS & set(section.data):
        section.error(
            key,
            f"a radius is not read here: give {diameter}, the wheel's DIAMETER in metres "
            "(2 × radius)",
        )


def parse_robots(
    top: Section, units: dict[str, UnitConfig], name_ok: Any
) -> dict[str, RobotConfig]:
    """Every robot of ``robots:``, checked against the units (``name_ok``: the pattern
    names must match)."""
    raw = top.data.get("robots")
    if raw is None:
        return {}
    if not isinstance(raw, list) or not raw:
        empty = " (an empty one: drop `robots:`)" if raw == [] else ""
        top.error("robots", f"expected a list of robots{empty}, each with name, track_m and wheels")
        return {}
    robots: dict[str, RobotConfig] = {}
    taken: dict[tuple[str, int], str] = {}  # (unit, axis) → the robot whose wheel it is
    for i, item in enumerate(raw):
        r = section(top.src, ("robots", i), item, ROBOT_KEYS, "diameter_m")
        robot = _robot(r, units, name_ok)
        if robot is None:
            continue
        if robot.name in robots:
            r.error("name", f"duplicate robot name '{robot.name}'")
            continue
        _claim(r, robot, taken)
        _one_turn(r, robot, units)
        robots[robot.name] = robot
    for index, robot in enumerate(robots.values()):
        foreign = robot.name in units and robot.name not in robot.units
        if foreign:
            top.src.error(
                ("robots", index, "name"),
                f"'{robot.name}' is the name of a unit that is not one of this robot's: "
                "robot and unit names must not be taken for each other",
            )
    _no_geometry(top, units, robots)
    return robots


def _robot(r: Section, units: dict[str, UnitConfig], name_ok: Any) -> RobotConfig | None:
    if not r.has("name"):
        r.error("name", "missing: every robot needs a name")
        return None
    name = r.text("name", "")
    if name and not name_ok.match(name):
        r.error("name", f"'{name}': robot names are letters, digits and '_', first a letter")
    if not r.has("track_m"):
        r.error("track_m", "missing: the distance between the left and right wheels [m]")
    track = r.number("track_m", 0.5, 0.001, 100, lo_open=True)
    defaults = (
        r.number("diameter_m", 0.0, 0.001, DIAMETER_MAX_M) if r.has("diameter_m") else None,
        r.number("gear_ratio", 1.0, 1e-6, 1e6, lo_open=True),
        r.number("pulses_per_rev", 0.0, 0, 1e9),
    )
    wheels = _wheels(r, units, defaults)
    lim = r.sub("limits", ROBOT_LIMIT_KEYS)
    limits = RobotLimits(
        *(
            lim.number(key, 0.0, 0, 1e3, lo_open=True) if lim.has(key) else None
            for key in ("linear_mps", "angular_radps", "linear_accel_mps2", "angular_accel_radps2")
        )
    )
    return RobotConfig(
        name=name,
        wheels=wheels,
        track_m=track,
        limits=limits,
        frame_id=_frame(r, "frame_id", "odom"),
        child_frame_id=_frame(r, "child_frame_id", "base_link"),
    )


def _frame(r: Section, key: str, default: str) -> str:
    value = r.text(key, default)
    if not set(value) <= FRAME_CHARS or value.startswith("/"):
        r.error(key, f"{value!r}: a frame id is letters, digits, '_' and '/', not first")
        return default
    return value


def _wheels(
    r: Section, units: dict[str, UnitConfig], defaults: tuple[float | None, float, float]
) -> tuple[Wheel, ...]:
    raw = r.data.get("wheels")
    if not isinstance(raw, list) or not raw:
        r.error("wheels", "expected a list of wheels (each with unit, axis and side)")
        return ()
    wheels: list[Wheel] = []
    for j, item in enumerate(raw):
        before = len(r.src.problems)
        w = section(r.src, (*r.path, "wheels", j), item, WHEEL_KEYS, "diameter_m")
        wheel = _wheel(w, units, defaults)
        if wheel is not None and len(r.src.problems) == before:
            wheels.append(wheel)
    sides = {w.side for w in wheels}
    if wheels and len(wheels) == len(raw) and sides != {Side.LEFT, Side.RIGHT}:
        missing = next(s for s in Side if s not in sides)
        r.error("wheels", f"no wheel on the {missing} side: a robot needs at least one each side")
    return tuple(wheels)


def _wheel(
    w: Section, units: dict[str, UnitConfig], defaults: tuple[float | None, float, float]
) -> Wheel | None:
    diameter, gear, pulses = defaults
    for key in ("unit", "axis", "side"):
        if not w.has(key):
            w.error(key, "missing: every wheel needs unit, axis (A or B) and side (left or right)")
            return None
    # A/B and left/right in any case: `axis: a` is no mistake worth stopping for
    for key in ("axis", "side"):
        if isinstance(w.data.get(key), str):
            w.data[key] = w.data[key].upper() if key == "axis" else w.data[key].lower()
    axis = w.choice("axis", "A", list(AXES))
    side = w.choice("side", "left", [s.value for s in Side])
    value = w.data.get("unit")
    unit = value if isinstance(value, str) else ""
    if not isinstance(value, str) or not value:
        w.error("unit", f"expected a unit's name, got {value!r}")
        return None
    if unit not in units:
        w.error("unit", f"no unit named {unit!r} (units: {', '.join(units) or 'none'})")
        return None
    if units[unit].role is not Role.COMMAND:
        w.error("unit", f"unit '{unit}' is role: monitor: it drives no wheel")
        return None
    sign = w.data.get("sign", 1)
    if sign not in (1, -1) or isinstance(sign, bool):
        w.error("sign", f"expected 1 (mounted forward) or -1 (mounted mirrored), got {sign!r}")
        sign = 1
    if not w.has("diameter_m") and diameter is None:
        w.error("diameter_m", "missing: the wheel's diameter [m], here or on the robot")
    return Wheel(
        unit=unit,
        axis=AXES.index(axis),
        side=Side(side),
        diameter_m=w.number("diameter_m", diameter or 0.1, 0.001, DIAMETER_MAX_M),
        gear_ratio=w.number("gear_ratio", gear, 1e-6, 1e6, lo_open=True),
        sign=int(sign),
        pulses_per_rev=w.number("pulses_per_rev", pulses, 0, 1e9),
    )


def _one_turn(r: Section, robot: RobotConfig, units: dict[str, UnitConfig]) -> None:
    """A robot's units on one bus send in the same turn: only at one command rate."""
    first: dict[str, str] = {}
    for j, wheel in enumerate(robot.wheels):
        cfg = units[wheel.unit]
        other = units[first.setdefault(cfg.bus, wheel.unit)]
        if other.command_rate_hz != cfg.command_rate_hz:
            r.src.error(
                (*r.path, "wheels", j, "unit"),
                f"unit '{cfg.name}' runs at command_rate_hz {cfg.command_rate_hz:g} and unit "
                f"'{other.name}' of the same robot and bus at {other.command_rate_hz:g}: a "
                "robot's drives send in the same turn, so give them one rate",
            )
            return


def _claim(r: Section, robot: RobotConfig, taken: dict[tuple[str, int], str]) -> None:
    """One robot per unit (its two axes' commands go in one frame) and per axis."""
    drives = {unit: name for (unit, _), name in taken.items()}
    seen: set[tuple[str, int]] = set()
    for j, wheel in enumerate(robot.wheels):
        key = (wheel.unit, wheel.axis)
        other = drives.get(wheel.unit)
        if other is not None:
            r.src.error(
                (*r.path, "wheels", j, "unit"),
                f"unit '{wheel.unit}' already drives robot '{other}': one unit, one robot "
                "(its two axes' commands go out in one frame)",
            )
        elif key in seen:
            r.src.error(
                (*r.path, "wheels", j, "axis"),
                f"axis {AXES[wheel.axis]} of unit '{wheel.unit}' is already a wheel of this robot",
            )
        seen.add(key)
    for key in seen:
        taken.setdefault(key, robot.name)


def _no_geometry(
    top: Section, units: dict[str, UnitConfig], robots: dict[str, RobotConfig]
) -> None:
    raw_units = top.data.get("units")
    if not isinstance(raw_units, list):
        return
    wheel_units = {u: r.name for r in robots.values() for u in r.units}
    for index, item in enumerate(raw_units):
        if isinstance(item, dict) and item.get("name") in wheel_units and "geometry" in item:
            top.src.error(
                ("units", index, "geometry"),
                f"unit '{item['name']}' is a wheel drive of robot '{wheel_units[item['name']]}': "
                "its wheels are described there (diameter_m, gear_ratio, pulses_per_rev); "
                "remove its geometry (docs/robots.md, migrating)",
            )
