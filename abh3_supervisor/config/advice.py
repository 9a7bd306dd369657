"""Warnings for a file that is valid but unsafe on real drives (``check`` and the log at
start): a real bus is one without ``simulate:``; what is harmless on the simulator —
no speed limit, motion at start — is said there, never refused (docs/robots.md). And one
that holds on the simulator too: two robots putting the same transform on one ``/tf``
(the ``ros2`` plugin), which tf2 would take as one frame jumping between two poses."""

from __future__ import annotations

from typing import Any

from abh3_supervisor.config.model import Config, Role, UnitConfig
from abh3_supervisor.config.source import Path, dotted
from abh3_supervisor.core.commands import CurrentCommand, VelocityCommand, parse_command
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol.scaling import VELOCITY


def warnings(config: Config) -> list[str]:
    """``FILE:LINE: key: why`` for each commanded unit on a real bus that has no speed
    limit (its own or its robot's) or moves at start, and for each robot whose transform
    another one already puts on the same ``/tf``."""
    out: list[str] = []
    for index, unit in enumerate(config.units.values()):
        bus = config.buses.get(unit.bus)
        if bus is None or bus.simulate is not None or unit.role is not Role.COMMAND:
            continue
        real = f"bus {bus.name} ({bus.interface} {bus.channel}) is a real bus"
        if not _limited(config, unit):
            out.append(
                _where(config, ("units", index, "limits"))
                + f"unit '{unit.name}' has no speed limit and {real}: a command may run its "
                f"motors up to {VELOCITY.largest:g} min⁻¹; set its limits.velocity or its "
                "robot's limits.linear_mps and angular_radps (low enough that its wheels' "
                "motors stay below that)"
            )
        moving = [text for text in unit.startup if _moves(text)]
        if moving:
            out.append(
                _where(config, ("units", index, "startup"))
                + f"unit '{unit.name}' moves at start ({', '.join(map(repr, moving))}) and "
                f"{real}: its motors turn the moment `run` starts, with no question asked; "
                "give motion from a client, or put it under the bus's simulate.startup"
            )
    return out + _shared_transforms(config)


def _shared_transforms(config: Config) -> list[str]:
    """``FILE:LINE: key: why`` for each robot whose ``frame_id → child_frame_id`` another
    robot already publishes on the same ``/tf`` (docs/ros2.md): every ``odom`` of the
    ``ros2`` plugin with its ``odom_tf`` on (the default), frame ids its own (a declared
    robot) or the plugin's ``odom_frame``/``base_frame`` (a unit's own robot)."""
    if "ros2" not in config.plugins:
        return []
    raw = _mapping(config.plugins.get("ros2"))
    robots, remap = _mapping(raw.get("robots")), _mapping(raw.get("remap"))
    namespace = raw.get("namespace", "/{unit}")
    namespace = namespace if isinstance(namespace, str) else "/{unit}"
    declared = [r for r in config.robots.values() if not r.implicit]
    wheels = {u for r in declared for u in r.units}
    # (name, frame ids, where it is in the file): every robot the bridge gives an odom
    publishing: list[tuple[str, tuple[str, str], Path]] = [
        (r.name, (r.frame_id, r.child_frame_id), ("robots", _index(config, r.name)))
        for r in declared
    ]
    frames = (str(raw.get("odom_frame", "odom")), str(raw.get("base_frame", "base_link")))
    publishing += [
        (u.name, frames, ("units", index))
        for index, u in enumerate(config.units.values())
        if u.name not in wheels and u.geometry.pulses_per_rev > 0
    ]
    first: dict[tuple[str, str, str], str] = {}
    out: list[str] = []
    for name, (frame_id, child), where in publishing:
        own = _mapping(robots.get(name))
        if own.get("odom_tf", raw.get("odom_tf", True)) is False:
            continue
        topic = remap.get(f"{name}/tf", remap.get("tf", "/tf"))
        if not isinstance(topic, str):
            continue  # reported by the plugin's own check
        if not topic.startswith("/"):  # relative: under the robot's namespace
            topic = f"{namespace.replace('{unit}', name).rstrip('/')}/{topic}"
        other = first.setdefault((topic, frame_id, child), name)
        if other != name:
            own_ids = (
                "declare it under robots: with its own frame_id and child_frame_id"
                if where[0] == "units"  # a unit's own robot: the plugin's frame ids
                else "give each robot its own frame_id and child_frame_id"
            )
            out.append(
                _where(config, where)
                + f"robot '{name}' publishes {frame_id} → {child} on {topic}, as robot "
                f"'{other}' does: tf2 would see one frame jumping between two poses; "
                f"{own_ids} (a prefix: {name}_odom, {name}_base_link), or set "
                f"plugins.ros2.robots.{name}.odom_tf: false where another node publishes "
                "that transform"
            )
    return out


def _mapping(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {}


def _index(config: Config, robot: str) -> int:
    """The robot's place in the file's ``robots:`` list (declared robots keep that order)."""
    return list(config.declared_robots).index(robot)


def _limited(config: Config, unit: UnitConfig) -> bool:
    """A limit below the wire's maximum binds every axis of the unit: its own, or the one
    its robot's limits give each of its wheels (robot limits that allow more than the
    wire can carry limit nothing)."""
    if unit.limits.velocity < VELOCITY.largest:
        return True
    robot = config.robot_of(unit.name)
    if robot is None:
        return False
    wheels = [w for w in robot.wheels if w.unit == unit.name]
    limits = [robot.axis_limit(w) for w in wheels]
    return bool(wheels) and all(x is not None and x < VELOCITY.largest for x in limits)


def _moves(text: str) -> bool:
    """A non-zero setpoint: a ``VEL``/``CUR`` that is not zero on both axes."""
    try:
        command = parse_command(text)
    except CommandError:
        return False
    return isinstance(command, VelocityCommand | CurrentCommand) and bool(command.ay or command.bx)


def _where(config: Config, path: Path) -> str:
    line = config.source.line(path) if config.source is not None else 1
    return f"{config.file}:{line}: {dotted(path)}: "


def odometry(config: Config) -> list[str]:
    """One line per robot with a ROS 2 ``odom`` (the ``ros2`` plugin configured): its rate
    and what its pose rests on (docs/ros2.md, "Odometry")."""
    section = config.plugins.get("ros2")
    if "ros2" not in config.plugins:
        return []
    raw = section if isinstance(section, dict) else {}
    robots = raw.get("robots")
    own: dict[str, Any] = robots if isinstance(robots, dict) else {}
    out: list[str] = []
    for robot in config.robots.values():
        units = [config.units[u] for u in robot.units if u in config.units]
        if (robot.implicit and not robot.odometry_ready) or not units:
            continue  # a one-drive robot without pulses_per_rev: no odom, as before
        command_hz = min(u.command_rate_hz for u in units)
        found = own.get(robot.name)
        mine: dict[str, Any] = found if isinstance(found, dict) else {}
        asked = mine.get("odom_rate_hz", raw.get("odom_rate_hz", 0)) or 0
        if not isinstance(asked, int | float) or isinstance(asked, bool):
            asked = 0  # reported by the plugin's own check
        rate = (
            f"{command_hz:g} Hz (the command rate)"
            if not asked or asked >= command_hz
            else f"{asked:g} Hz (odom_rate_hz; the command rate is {command_hz:g} Hz)"
        )
        blind = [w.name for w in robot.wheels if w.pulses_per_rev <= 0]
        silent = [u.name for u in units if 4 not in u.broadcast.packets]
        if blind or silent:
            why = (
                f"wheel {', '.join(blind)} without pulses_per_rev"
                if blind
                else f"unit {', '.join(silent)} without bit 4 in broadcast.mask"
            )
            source = f"velocity feedback integrated ({why})"
        else:
            hz = min(u.broadcast.rate_hz / len(u.broadcast.packets) for u in units)
            source = (
                f"pulse counts (broadcast 4, about {hz:g} Hz), velocity feedback "
                "integrated between them"
            )
        out.append(f"robot {robot.name}: odom at {rate}; pose from {source}")
    return out
