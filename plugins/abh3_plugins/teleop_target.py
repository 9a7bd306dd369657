"""What a teleop plugin (keyboard, joystick) drives: robots, each as a whole.

Its section names them with ``robot: NAME`` and/or ``units: [NAMES]``, where a name is a
robot or a unit (a unit stands for the robot whose drive it is: a file without
``robots:`` has one robot per commanded unit, named after it). The plugin's input source
targets every unit of those robots, so its twist drives all their drives together, and
the fastest twist its keys or stick may ask is the robots' (core/twist_limits.py).
"""

from __future__ import annotations

import difflib
import math

from abh3_supervisor.plugin_api import Config, RobotConfig, Section, fastest_twist

KEYS = {"robot", "units"}


def robots(section: Section, config: Config, what: str) -> tuple[RobotConfig, ...]:
    """The robots ``section`` names (``what``: the plugin, for the messages)."""
    named: list[tuple[str, tuple[str | int, ...]]] = []
    if section.has("robot"):
        named.append((section.text("robot", ""), ("robot",)))
    if section.has("units"):
        named += [(n, ("units", i)) for i, n in enumerate(section.strings("units", ()))]
    if not section.has("robot") and not section.has("units"):
        section.error(
            "units",
            f"missing: name the robot the {what} drives (robot: NAME) or its units (units: [left])",
        )
    found: dict[str, RobotConfig] = {}
    for name, where in named:
        robot = config.robot(name)
        if robot is not None:
            found[robot.name] = robot
        elif name:
            section.src.error((*section.path, *where), _unknown(name, config))
    return tuple(found.values())


def _unknown(name: str, config: Config) -> str:
    if name in config.units:
        return f"unit '{name}' is role: monitor: it drives no robot"
    declared = [r.name for r in config.robots.values() if not r.implicit]
    wheels = [u for r in config.robots.values() for u in r.units]
    hint = difflib.get_close_matches(name, [*declared, *wheels], n=1)
    did = f"; did you mean '{hint[0]}'?" if hint else ""
    listed = f"robots: {', '.join(declared)}; " if declared else ""
    return f"no robot or unit named {name!r} ({listed}units: {', '.join(wheels) or 'none'}){did}"


def units(targets: tuple[RobotConfig, ...]) -> tuple[str, ...]:
    """Every unit of the robots: what the plugin's input source targets."""
    return tuple(u for robot in targets for u in robot.units)


def fastest(targets: tuple[RobotConfig, ...], config: Config) -> tuple[float, float]:
    """The fastest twist every one of the robots may go: (linear m/s, angular rad/s)."""
    speed = turn = math.inf
    for robot in targets:
        v, w = fastest_twist(robot, config.units)
        speed, turn = min(speed, v), min(turn, w)
    return speed, turn


def limit(twist: tuple[float, float], most: tuple[float, float]) -> tuple[float, float]:
    """``twist`` within ``most``, both parts scaled alike (the path's curvature kept)."""
    scale = min([1.0, *(m / abs(v) for v, m in zip(twist, most, strict=True) if v)])
    return twist[0] * scale, twist[1] * scale
