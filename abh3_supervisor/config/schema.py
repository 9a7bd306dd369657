"""The configuration as a JSON Schema (draft 2020-12), for editors and other tools.

The builders mirror :class:`~abh3_supervisor.config.source.Section`'s typed getters, so a
section's schema reads like the code that parses it, and plugins describe their own
section with the same words (``abh3_config_schema``). The schema holds types, ranges,
choices and key names; what needs the whole file (unique names and addresses, timing
rules, startup commands, writable paths, the bus-load plan) stays with ``abh3 check``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from abh3_supervisor.config import parse
from abh3_supervisor.config.endpoint import MAX_PORT
from abh3_supervisor.config.endpoint import PATTERN as ENDPOINT_PATTERN
from abh3_supervisor.config.interfaces import known_interfaces
from abh3_supervisor.config.model import (
    AXIS_KINDS,
    MAX_UNITS_PER_TURN,
    UNITS_PER_TURN,
    WIRING_KINDS,
    ControlMode,
    FaultKind,
    Role,
    VelocityModel,
    VerifyMode,
)
from abh3_supervisor.config.robots import DIAMETER_MAX_M
from abh3_supervisor.config.source import MAX_BYTES
from abh3_supervisor.core.robot import AXES, Side
from abh3_supervisor.params.telabh3 import DEFAULT_FORMAT, Checksum
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.protocol.ids import MAX_ADDRESS
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY

Schema = dict[str, Any]
DIALECT = "https://json-schema.org/draft/2020-12/schema"
NAME_PATTERN = parse.NAME.pattern


def _doc(schema: Schema, description: str, default: Any) -> Schema:
    if description:
        schema["description"] = description
    if default is not None:
        schema["default"] = default
    return schema


def integer(lo: int, hi: int, description: str = "", default: int | None = None) -> Schema:
    """As ``Section.integer``: a whole number (never true/false) within lo–hi."""
    return _doc({"type": "integer", "minimum": lo, "maximum": hi}, description, default)


def number(
    lo: float,
    hi: float,
    description: str = "",
    default: float | None = None,
    *,
    lo_open: bool = False,
) -> Schema:
    """As ``Section.number``: any finite number, above ``lo`` when ``lo_open``."""
    bound = "exclusiveMinimum" if lo_open else "minimum"
    return _doc({"type": "number", bound: lo, "maximum": hi}, description, default)


def boolean(description: str = "", default: bool | None = None) -> Schema:
    return _doc({"type": "boolean"}, description, default)


def text(description: str = "", default: str | None = None) -> Schema:
    """As ``Section.text``: a non-empty string."""
    return _doc({"type": "string", "minLength": 1}, description, default)


def names(description: str = "") -> Schema:
    """As ``Section.strings``/``.units``: a non-empty list of non-empty strings."""
    return _doc(
        {"type": "array", "minItems": 1, "items": {"type": "string", "minLength": 1}},
        description,
        None,
    )


def choice(
    choices: Sequence[str | int], description: str = "", default: str | None = None
) -> Schema:
    return _doc({"enum": list(choices)}, description, default)


def mapping(
    properties: dict[str, Schema], description: str = "", *, required: tuple[str, ...] = ()
) -> Schema:
    """A mapping of exactly these keys (unknown keys are errors, as ``Section.only``);
    an empty value (``key:`` alone) counts as an empty mapping, as the loader reads it."""
    schema: Schema = {
        "type": ["object", "null"],
        "properties": properties,
        "additionalProperties": False,
    }
    if required:
        schema["type"] = "object"
        schema["required"] = list(required)
    return _doc(schema, description, None)


def free_mapping(description: str = "") -> Schema:
    return _doc({"type": ["object", "null"]}, description, None)


def _bus() -> Schema:
    sim = mapping(
        {
            "command_zero_timeout_ms": integer(
                0, 60_000, "every simulated drive's command-zero timeout; 0 = off"
            ),
            "error_timeout_ms": integer(0, 60_000, default=1000),
            "accel": number(0, 1e6, "min⁻¹ per second", 3000.0, lo_open=True),
            "time_constant_ms": number(
                0, 60_000, "a first-order velocity response instead of the ramp", lo_open=True
            ),
            "unit_time_constant_ms": {
                "type": "object",
                "description": "per unit, its drive's own velocity time constant [ms]",
                "additionalProperties": number(0, 60_000, lo_open=True),
            },
            "startup": {
                "type": "object",
                "description": "per unit, commands run at start after its own startup, only "
                "while this bus is simulated (a real bus never runs them)",
                "additionalProperties": {"type": "array", "items": {"type": "string"}},
            },
            "external": boolean(
                "the drives run in `abh3 simulate`, a process of their own on this bus's "
                "interface; every other command opens the bus as a real one (default: true "
                "on udp_multicast, false elsewhere)"
            ),
            "reply_latency_ms": number(0, 10_000, default=0.2),
            "dp0_period_ms": integer(0, 1000, "> 0: DP0 replies also periodically", 0),
            "broadcast_period_ms": integer(0, 1000, "> 0: broadcasts also periodically", 0),
            "faults": {"type": "array", "items": _fault()},
            "params": {
                "type": "object",
                "description": "per unit, drive parameters that differ from the file "
                "(address: a name of the table or hex; value: a number), to rehearse a "
                "mismatch",
                "additionalProperties": {
                    "type": "object",
                    "minProperties": 1,
                    "additionalProperties": {"type": "number"},
                },
            },
            "telabh3_form": {
                "type": "object",
                "description": "per unit, the only TelABH3 string form its drive reads "
                "({header, checksum}), none or any (the default)",
                "additionalProperties": {"anyOf": [_form(), choice(["none", "any"])]},
            },
        },
        "simulator options",
    )
    sim["type"] = "object"  # `simulate:` with no value is an error, never "on"
    return mapping(
        {
            # python-can's list on the machine that writes the schema, as `check` uses it
            "interface": choice(
                sorted(known_interfaces()),
                "python-can interface (its built-ins and installed ones, e.g. wacousb)",
                "socketcan",
            ),
            "channel": {
                "anyOf": [{"type": "string", "minLength": 1}, {"type": "integer"}],
                "description": "python-can channel: one name or number",
                "default": "can0",
            },
            "bitrate": choice_of_ints(list(parse.BITRATES), "bit/s", 500_000),
            "units_per_turn": integer(
                1,
                MAX_UNITS_PER_TURN,
                "units whose commands leave together in one turn (1: each its own phase)",
                UNITS_PER_TURN,
            ),
            "simulate": {
                "anyOf": [{"type": "boolean"}, sim],
                "description": "attach the built-in simulator: true or its options",
                "default": False,
            },
            "options": {
                "type": ["object", "null"],
                "description": "extra keyword arguments for can.Bus(...)",
                "not": {"anyOf": [{"required": [k]} for k in sorted(parse.BUS_ARGUMENTS)]},
            },
        }
    )


def _form() -> Schema:
    return mapping(
        {
            "header": boolean("send the FFFF header of the serial form", DEFAULT_FORMAT.header),
            "checksum": choice(
                [c.value for c in Checksum],
                "what the checksum covers",
                DEFAULT_FORMAT.checksum.value,
            ),
        }
    )


def choice_of_ints(values: list[int], description: str, default: int) -> Schema:
    return {"type": "integer", "enum": values, "description": description, "default": default}


def _fault() -> Schema:
    fault = mapping(
        {
            "kind": choice([k.value for k in FaultKind]),
            "at_s": number(0, 7 * 86400.0, "start, seconds after the run's start (wiring: 0)"),
            "for_s": number(0, 7 * 86400.0, "how long [s] (wiring: for ever)", lo_open=True),
            "unit": text("only this unit (not for bus_send_error)"),
            "bits": integer(1, 0xFFFFFFFF, "error_bits: which error bits", 0x40),
            "delay_ms": number(0, 10_000, "slow_replies: how late", 50.0, lo_open=True),
            "axis": choice(
                ["A", "B"], "the motor (reversed_axis, scale, no_encoder, mirrored_wheel)"
            ),
            "factor": number(
                0,
                100,
                "scale: pulses per pulse the geometry expects; wrong_track, wrong_diameter: "
                "the true value per the file's",
                lo_open=True,
            ),
            "other": text("swapped_drives: the unit on whose wheels `unit`'s drive sits"),
        },
        required=("kind",),
    )
    timed = [k.value for k in FaultKind if k not in WIRING_KINDS]
    axis = [k.value for k in AXIS_KINDS]
    fault["allOf"] = [  # timed faults say when; wiring faults say where
        {
            "if": {"properties": {"kind": {"enum": timed}}},
            "then": {"required": ["at_s", "for_s"]},
        },
        {"if": {"properties": {"kind": {"enum": axis}}}, "then": {"required": ["axis"]}},
        {
            "if": {"properties": {"kind": {"enum": ["scale", "wrong_track", "wrong_diameter"]}}},
            "then": {"required": ["factor"]},
        },
        {
            "if": {"properties": {"kind": {"const": "swapped_drives"}}},
            "then": {"required": ["unit", "other"]},
        },
    ]
    return fault


def _unit() -> Schema:
    protocols = [g.value for g in Generation]
    return mapping(
        {
            "name": {"type": "string", "pattern": NAME_PATTERN, "description": "unique"},
            "bus": text("a declared bus; may be left out when only one is declared"),
            "abh3_id": integer(0, MAX_ADDRESS, "the drive's address", 1),
            "host_id": integer(0, MAX_ADDRESS, "our address toward this drive", 2),
            "priority": integer(0, 7, "J1939 priority of our frames", 0),
            "brd_group": integer(0, 31, "the drive's broadcast group", 5),
            # choice() reads str(value): protocol: 2021 unquoted is accepted too
            "protocol": choice(
                [*protocols, *(int(p) for p in protocols)],
                "the drive's generation: every flag word's bit layout",
                "2021",
            ),
            "timeout_ms": integer(1, 60_000, "no answer this long → offline", 1000),
            "reply_timeout_ms": integer(1, 60_000, "longest wait for one DP0 reply", 100),
            "drive_timeout_ms": integer(10, 60_000, "the drive's command-zero timeout", 500),
            "command_rate_hz": number(1, 1000, "DP0 exchanges per second", 50.0),
            "control": choice([m.value for m in ControlMode], default="velocity"),
            "velocity_model": choice([m.value for m in VelocityModel], default="travel"),
            "role": choice([r.value for r in Role], default="command"),
            "broadcast": mapping(
                {
                    "mask": integer(0, 0x7F, "status packets 0–6 to poll", 0x7F),
                    "rate_hz": number(0.01, 1000, "status requests per second", 10.0),
                    "listen_only": boolean("never poll", False),
                }
            ),
            "geometry": mapping(
                {
                    "rate_num": number(1e-6, 1e6, "gear ratio numerator", 1.0),
                    "rate_den": number(1e-6, 1e6, "gear ratio denominator", 10.0),
                    "wheel": number(0.001, 100, "wheel diameter [m]", 0.1),
                    "width": number(0.001, 100, "wheel track [m]", 0.5),
                    "pulses_per_rev": number(0, 1e9, "encoder pulses per motor turn", 0.0),
                }
            ),
            "limits": mapping(
                {
                    "velocity": number(0, VELOCITY.largest, "min⁻¹ per axis", lo_open=True),
                    "current": number(0, CURRENT.largest, "% per axis", lo_open=True),
                }
            ),
            "data_select": mapping(
                {"ay": integer(0, 7, default=7), "bx": integer(0, 7, default=7)}
            ),
            "startup": {
                "type": "array",
                "items": {"type": "string"},
                "description": "the seed's command language, applied once at start",
            },
            # docs/parameters.md: public sources do not settle it; without: found at first use
            "telabh3": _doc(_form(), "the TelABH3 string form; without: found at first use", None),
            # a bare `off` is YAML 1.1's false, read as "off"
            "verify": choice(
                [*(m.value for m in VerifyMode), False],
                "read the drive's CAN settings at start and compare them with this file",
                VerifyMode.WARN.value,
            ),
        },
        required=("name",),
    )


def _robot() -> Schema:
    diameter = number(0.001, DIAMETER_MAX_M, "the wheel's DIAMETER [m] (not its radius)")
    gear = number(1e-6, 1e6, "motor revolutions per wheel revolution (10:1 → 10)", lo_open=True)
    pulses = number(0, 1e9, "encoder pulses per motor revolution; 0: unknown", 0.0)
    wheel = mapping(
        {
            "unit": text("a declared commanded unit"),
            "axis": choice(list(AXES), "the unit's axis this wheel's motor is on"),
            "side": choice([s.value for s in Side], "the robot's side this wheel is on"),
            "sign": {
                "enum": [1, -1],
                "default": 1,
                "description": "1: the motor forward rolls the robot forward; -1: mirrored",
            },
            "diameter_m": diameter,
            "gear_ratio": gear,
            "pulses_per_rev": pulses,
        },
        required=("unit", "axis", "side"),
    )
    limit = "the robot's limit; a twist beyond it is scaled down, path kept"
    return mapping(
        {
            "name": {"type": "string", "pattern": NAME_PATTERN, "description": "unique"},
            "track_m": number(
                0.001, 100, "distance between left and right wheels [m]", lo_open=True
            ),
            "wheels": {"type": "array", "minItems": 2, "items": wheel},
            "limits": mapping(
                {
                    "linear_mps": number(0, 1e3, f"[m/s] {limit}", lo_open=True),
                    "angular_radps": number(0, 1e3, f"[rad/s] {limit}", lo_open=True),
                    "linear_accel_mps2": number(0, 1e3, "[m/s²] speeding up", lo_open=True),
                    "angular_accel_radps2": number(0, 1e3, "[rad/s²] speeding up", lo_open=True),
                }
            ),
            "frame_id": text("the odometry's frame", "odom"),
            "child_frame_id": text("the robot's body frame", "base_link"),
            "diameter_m": diameter,
            "gear_ratio": _doc(dict(gear), "", 1.0),
            "pulses_per_rev": pulses,
        },
        required=("name", "track_m", "wheels"),
    )


ON_ERROR_VALUES = ("continue", "stop")  # every plugin section's on_error (plugin_host)
ON_ERROR = choice(
    list(ON_ERROR_VALUES),
    "what a failure of the plugin (any exception, a failed output) does to the run",
    "continue",
)
# every plugin section's critical (plugin_host): the plugin disabled ends the run
CRITICAL = boolean("the run ends (drives stopped, non-zero exit) if this plugin is disabled", False)
# every plugin section's tick_hz (plugin_host/tick.py): the rate of its abh3_tick
TICK_HZ = number(0, 100, "how often abh3_tick is called [Hz]", 10.0, lo_open=True)
# every plugin section's start_timeout_s (plugin_host): how long its start may take
START_TIMEOUT_S = number(
    0, 600, "how long abh3_start, abh3_input_sources and each input's start may take [s]", 5.0,
    lo_open=True,
)  # fmt: skip
# the host's keys, in every plugin section
HOST_KEYS = {
    "on_error": ON_ERROR,
    "critical": CRITICAL,
    "tick_hz": TICK_HZ,
    "start_timeout_s": START_TIMEOUT_S,
}


def plugin_section(schema: Schema | None, description: str) -> Schema:
    """A plugin's section: its own schema plus the host's ``on_error``, ``critical``,
    ``tick_hz`` and ``start_timeout_s``; free-form when the plugin gives none."""
    if schema is None:
        section = free_mapping(description)
        section["properties"] = dict(HOST_KEYS)
        return section
    section = dict(schema)
    section["properties"] = {**schema.get("properties", {}), **HOST_KEYS}
    return _doc(section, description, None)


def document(plugins: dict[str, Schema]) -> Schema:
    """The whole file's schema; ``plugins`` maps each installed plugin to its section's."""
    return {
        "$schema": DIALECT,
        "title": "abh3-supervisor configuration",
        "description": (
            f"buses, units and plugins (at most {MAX_BYTES >> 10} KiB); `abh3 check` also "
            "checks names, addresses, timing rules and the bus-load plan"
        ),
        "type": "object",
        "properties": {
            "buses": {
                "type": "object",
                "minProperties": 1,
                "propertyNames": {"pattern": NAME_PATTERN},
                "additionalProperties": _bus(),
            },
            "units": {"type": "array", "minItems": 1, "items": _unit()},
            "robots": {
                "type": "array",
                "minItems": 1,
                "items": _robot(),
                "description": "robots made of wheels on any units' axes (docs/robots.md)",
            },
            "plugins": {
                "type": ["object", "null"],
                "properties": plugins,
                "additionalProperties": False,
                "description": "only the plugins named here run",
            },
            "stop_ramp_s": {
                "type": "number",
                "minimum": 0,
                "maximum": 10,
                "default": 1.0,
                "description": "the way out: START off and zero at once, SERVO and brake "
                "release off once each drive reports standing, at the latest after this long "
                "(0: at once; docs/safety.md)",
            },
            "foxglove": {
                "anyOf": [
                    {"type": "integer", "minimum": 0, "maximum": MAX_PORT},
                    {"type": "string", "pattern": ENDPOINT_PATTERN},
                ],
                "description": "serve the recording's topics live to Foxglove at [HOST:]PORT "
                "(127.0.0.1 unless a host is given; docs/foxglove.md; the foxglove extra)",
            },
        },
        "required": ["buses", "units"],
        "additionalProperties": False,
    }
