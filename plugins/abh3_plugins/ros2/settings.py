"""The ``plugins.ros2`` section of the YAML file, validated, and the topic names it gives."""

from __future__ import annotations

import dataclasses
import difflib
import re
from dataclasses import dataclass, field
from typing import Any

from abh3_supervisor.plugin_api import Config, RobotConfig, Role, Section, UnitConfig
from abh3_supervisor.plugin_api import schema as js

# every name the bridge uses, per unit: the seed's names; plus per robot cmd_vel, odom and
# the enable service (a one-drive robot from a unit's geometry is named after its unit)
COMMANDS = ("vel_cmd", "cur_cmd", "cmd_vel", "inp_data", "inp_service", "enable")
NAMES = (
    *COMMANDS,
    "vel_fbk_ab",
    "vel_fbk_yx",
    "brd_num",
    *(f"brd{n}_data" for n in range(7)),
    "xa",
    "xa_yx",
    "xa_ab",
    "yx",
    "yx_xa",
    "yx_ab",
    "ab",
    "ab_yx",
    "ab_xa",
    "odom",
    "joint_states",
    "joint_commands",
    "tf",
)
# the ROS 2 releases whose Nav2 the bridge knows: from Kilted on it publishes TwistStamped
DISTROS = ("humble", "jazzy", "kilted", "rolling")
STAMPED_FROM = "kilted"
ROBOT_KEYS = {"odom_rate_hz", "odom_tf", "cmd_vel_stamped", "joint_states", "joints"}
_JOINT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass(frozen=True)
class QosSettings:
    reliability: str = "reliable"  # or best_effort
    durability: str = "volatile"  # or transient_local
    depth: int = 10


CONVERSION_OUT = ("xa_yx", "xa_ab", "yx_xa", "yx_ab", "ab_yx", "ab_xa")


@dataclass(frozen=True)
class RobotSettings:
    """One robot's odometry, tf, joint and cmd_vel settings (docs/ros2.md): the section's,
    with the robot's own under ``robots: {<robot>: …}`` taking precedence."""

    odom_rate_hz: float = 0.0  # 0: the robot's command rate; else at most that
    odom_tf: bool = True  # odom → base_link on /tf, as diff_drive_controller's enable_odom_tf
    cmd_vel_stamped: bool = False  # geometry_msgs/TwistStamped, else Twist
    joint_states: bool = True  # sensor_msgs/JointState out, and (allow_commands) in
    joints: dict[str, str] = field(default_factory=dict)  # "<unit>.<A|B>" → joint name


def joint_name(unit: str, axis: str) -> str:
    """A wheel's default joint name: ``<unit>_<axis>_wheel_joint`` (``left_a_wheel_joint``)."""
    return f"{unit}_{axis.lower()}_wheel_joint"


@dataclass(frozen=True)
class Settings:
    domain_id: int = 0
    namespace: str = "/{unit}"  # {unit} is replaced by each unit's (or robot's) name
    transport: str = "auto"  # rclpy when importable, else dds
    conversion: bool = True
    allow_commands: bool = False
    command_timeout: float = 0.5  # [s] silence on vel_cmd/cur_cmd/cmd_vel → zero
    priority: int = 0
    status: str = "poll"  # poll: every packet received; request: answers to brd_num only
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    diagnostics_hz: float = 1.0  # /diagnostics, as ROS drivers publish it; 0: off
    # ros_discovery_info over plain DDS, so `ros2 node list` sees us: the GID layout of
    # humble, or of jazzy (Iron and later); off: none
    discovery: str = "jazzy"
    qos: QosSettings = field(default_factory=QosSettings)
    remap: dict[str, str] = field(default_factory=dict)
    distro: str = "jazzy"  # the ROS 2 release of the other nodes (Nav2's cmd_vel type)
    robot: RobotSettings = field(default_factory=RobotSettings)  # every robot's
    robots: dict[str, RobotSettings] = field(default_factory=dict)  # a robot's own

    def of(self, robot: str) -> RobotSettings:
        """``robot``'s settings: its own, else the section's."""
        return self.robots.get(robot, self.robot)

    def tf_name(self, robot: str) -> str:
        """Where ``robot``'s transform goes: ``/tf``, unless remapped."""
        target = self.remap.get(f"{robot}/tf", self.remap.get("tf", "/tf"))
        return target if target.startswith("/") else self.name(robot, target)

    def name(self, unit: str, name: str) -> str:
        """The fully qualified ROS name of ``name`` for ``unit`` (or a robot: its
        ``cmd_vel`` and ``odom``), after remapping.

        A remap key is a bare name (every unit) or ``<unit>/<name>`` (that unit, first);
        a relative target goes under the unit's namespace, an absolute one is used as is.
        """
        target = self.remap.get(f"{unit}/{name}", self.remap.get(name, name))
        if target.startswith("/"):
            return target
        return f"{self.namespace.format(unit=unit).rstrip('/')}/{target}"


def parse(section: Section, config: Config) -> Settings:
    section.only(
        {
            "domain_id",
            "namespace",
            "transport",
            "conversion",
            "allow_commands",
            "command_timeout_ms",
            "priority",
            "status",
            "odom_frame",
            "base_frame",
            "diagnostics_hz",
            "discovery",
            "qos",
            "remap",
            "distro",
            "robots",
            *ROBOT_KEYS - {"joints"},
        }
    )
    d = Settings()
    q = section.sub("qos", {"reliability", "durability", "depth"})
    settings = Settings(
        domain_id=section.integer("domain_id", d.domain_id, 0, 232),
        namespace=section.text("namespace", d.namespace),
        transport=section.choice("transport", d.transport, ["auto", "rclpy", "dds"]),
        conversion=section.boolean("conversion", d.conversion),
        allow_commands=section.boolean("allow_commands", d.allow_commands),
        command_timeout=section.integer("command_timeout_ms", 500, 10, 60_000) / 1000,
        priority=section.integer("priority", d.priority, -1000, 1000),
        status=section.choice("status", d.status, ["poll", "request"]),
        odom_frame=section.text("odom_frame", d.odom_frame),
        base_frame=section.text("base_frame", d.base_frame),
        diagnostics_hz=section.number("diagnostics_hz", d.diagnostics_hz, 0.0, 100.0),
        discovery=section.choice("discovery", d.discovery, ["jazzy", "humble", "off"]),
        qos=QosSettings(
            reliability=q.choice("reliability", "reliable", ["reliable", "best_effort"]),
            durability=q.choice("durability", "volatile", ["volatile", "transient_local"]),
            depth=q.integer("depth", 10, 1, 10_000),
        ),
        remap=_remap(section.sub("remap", None)),
        distro=section.choice("distro", d.distro, list(DISTROS)),
    )
    stamped = DISTROS.index(settings.distro) >= DISTROS.index(STAMPED_FROM)
    every = _robot_settings(section, RobotSettings(cmd_vel_stamped=stamped), config, None)
    robots = {}
    own = section.sub("robots", None)
    for name, _ in own.items():
        if name not in config.robots:
            known = ", ".join(config.robots) or "none"
            own.error(name, f"no robot named {name!r} (robots: {known})")
            continue
        robots[name] = _robot_settings(own.sub(name, ROBOT_KEYS), every, config, name)
    settings = dataclasses.replace(settings, robot=every, robots=robots)
    _check_names(section, settings, config)
    return settings


def _robot_settings(
    s: Section, d: RobotSettings, config: Config, robot: str | None
) -> RobotSettings:
    joints: dict[str, str] = {}
    if robot is not None:
        wheels = {w.name: w for w in config.robots[robot].wheels}
        js = s.sub("joints", None)
        for key, value in js.items():
            if key not in wheels:
                js.error(key, f"not a wheel of robot {robot} (wheels: {', '.join(wheels)})")
            elif not isinstance(value, str) or not _JOINT.match(value):
                js.error(key, f"{value!r} is not a joint name (letters, digits, _)")
            else:
                joints[key] = value
        taken: dict[str, str] = {}
        for w in config.robots[robot].wheels:
            name = joints.get(w.name, joint_name(w.unit, w.name[-1]))
            if taken.setdefault(name, w.name) != w.name:
                js.error(w.name, f"joint {name!r} is also wheel {taken[name]}'s")
    return RobotSettings(
        odom_rate_hz=s.number("odom_rate_hz", d.odom_rate_hz, 0.0, 1000.0),
        odom_tf=s.boolean("odom_tf", d.odom_tf),
        cmd_vel_stamped=s.boolean("cmd_vel_stamped", d.cmd_vel_stamped),
        joint_states=s.boolean("joint_states", d.joint_states),
        joints=joints,
    )


def schema() -> dict[str, Any]:
    """The section's JSON Schema: the same keys, types and ranges as :func:`parse`."""
    d = Settings()
    ros_name = {"type": "string", "pattern": _NAME.pattern}
    return js.mapping(
        {
            "domain_id": js.integer(0, 232, "DDS / ROS domain", d.domain_id),
            "namespace": js.text("absolute; {unit} stands for each unit's name", d.namespace),
            "transport": js.choice(["auto", "rclpy", "dds"], default=d.transport),
            "conversion": js.boolean("serve the conversion node's topics", d.conversion),
            "allow_commands": js.boolean("accept commands from ROS 2", d.allow_commands),
            "command_timeout_ms": js.integer(10, 60_000, "silence → zero", 500),
            "priority": js.integer(-1000, 1000, "in the input arbitration", d.priority),
            "status": js.choice(["poll", "request"], default=d.status),
            "odom_frame": js.text(default=d.odom_frame),
            "base_frame": js.text(default=d.base_frame),
            "diagnostics_hz": js.number(0.0, 100.0, "/diagnostics rate; 0: off", 1.0),
            "discovery": js.choice(
                ["jazzy", "humble", "off"],
                "ros_discovery_info for this ROS release's GID size (jazzy: Iron and later)",
                d.discovery,
            ),
            "qos": js.mapping(
                {
                    "reliability": js.choice(["reliable", "best_effort"], default="reliable"),
                    "durability": js.choice(["volatile", "transient_local"], default="volatile"),
                    "depth": js.integer(1, 10_000, "keep-last depth", 10),
                }
            ),
            "distro": js.choice(
                list(DISTROS),
                "the ROS 2 release of the other nodes: cmd_vel_stamped's default",
                d.distro,
            ),
            **_robot_schema(),
            "robots": {
                "type": ["object", "null"],
                "description": "a robot's own odometry, tf, joint and cmd_vel settings",
                "additionalProperties": js.mapping(
                    {
                        **_robot_schema(),
                        "joints": {
                            "type": ["object", "null"],
                            "description": "<unit>.<A|B>: the wheel's joint name",
                            "additionalProperties": {"type": "string", "pattern": _JOINT.pattern},
                        },
                    }
                ),
            },
            "remap": {
                "type": ["object", "null"],
                "description": "name: target, for every unit, or <unit>/name: target",
                "propertyNames": {"pattern": rf"^([A-Za-z][A-Za-z0-9_]*/)?({'|'.join(NAMES)})$"},
                "additionalProperties": ros_name,
            },
        }
    )


def _robot_schema() -> dict[str, Any]:
    d = RobotSettings()
    return {
        "odom_rate_hz": js.number(0.0, 1000.0, "odom and tf per second; 0: the command rate", 0.0),
        "odom_tf": js.boolean("publish odom → base_link on /tf", d.odom_tf),
        "cmd_vel_stamped": js.boolean(
            "cmd_vel is geometry_msgs/TwistStamped (default: false up to Jazzy, true from "
            "Kilted on, as Nav2 publishes it)",
            False,
        ),
        "joint_states": js.boolean("joint_states out and joint_commands in", d.joint_states),
    }


def _remap(section: Section) -> dict[str, str]:
    out: dict[str, str] = {}
    for key, target in section.items():
        name = key.rsplit("/", 1)[-1]
        if name not in NAMES or key.count("/") > 1:
            hint = difflib.get_close_matches(name, NAMES, n=1)
            did = f"did you mean '{hint[0]}'? " if hint else ""
            section.error(key, f"not a name of the bridge; {did}(names: {', '.join(NAMES)})")
        elif not isinstance(target, str) or not _NAME.match(target):
            section.error(key, f"{target!r} is not a ROS name like cmd or /robot/cmd")
        else:
            out[key] = target
    return out


def outputs(settings: Settings, unit: UnitConfig) -> list[str]:
    """The names a unit publishes or serves: no two units may share one."""
    names = ["vel_fbk_ab", "vel_fbk_yx", *(f"brd{n}_data" for n in unit.broadcast.packets)]
    if unit.geometry.pulses_per_rev > 0:
        names.append("odom")
        if unit.role is Role.COMMAND and settings.of(unit.name).joint_states:
            names.append("joint_states")
    if settings.conversion:
        names += CONVERSION_OUT
    if settings.allow_commands and unit.role is Role.COMMAND:
        names += ["inp_service", "enable"]
    return names


def robot_outputs(robot: RobotConfig, settings: Settings) -> list[str]:
    """The names a declared robot publishes or serves (its ``cmd_vel`` is an input)."""
    own = settings.of(robot.name)
    return ["odom", *["joint_states"] * own.joint_states, *["enable"] * settings.allow_commands]


def _check_names(section: Section, settings: Settings, config: Config) -> None:
    """Every unit's and robot's names must be valid ROS names, and its outputs its own.

    Inputs may be shared on purpose (one ``/cmd_vel`` for both drives of a robot).
    """
    declared = {r.name: r for r in config.robots.values() if not r.implicit}
    named = [*(("unit", u) for u in config.units), *(("robot", r) for r in declared)]
    try:
        spaces = {(kind, n): settings.namespace.format(unit=n) for kind, n in named}
    except (KeyError, IndexError, ValueError):
        section.error("namespace", f"{settings.namespace!r}: only {{unit}} may stand in braces")
        return
    for (kind, name), space in spaces.items():
        if not (space == "/" or (space.startswith("/") and _NAME.match(space))):
            section.error(
                "namespace",
                f"{space!r} ({kind} {name}) is not an absolute ROS name like /robot/{{unit}}: "
                "ROS names take letters, digits and _",
            )
            return
    publishes = [
        *((f"unit {u}", u, outputs(settings, cfg)) for u, cfg in config.units.items()),
        *((f"robot {r}", r, robot_outputs(robot, settings)) for r, robot in declared.items()),
    ]
    owner: dict[str, str] = {}
    for who, space_of, names in publishes:
        for name in names:
            full = settings.name(space_of, name)
            other = owner.setdefault(full, who)
            if other != who:
                key = "namespace" if "{unit}" not in settings.namespace else "remap"
                section.error(
                    key,
                    f"{_both(other, who)} would both publish {full}: "
                    "put {unit} in the namespace, or remap one of them",
                )
                return


def _both(first: str, second: str) -> str:
    """'units a and b', or 'unit a and robot r'."""
    if first.startswith("unit ") and second.startswith("unit "):
        return f"units {first[5:]} and {second[5:]}"
    return f"{first} and {second}"
