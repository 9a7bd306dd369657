"""Build a :class:`Config` from YAML, collecting every problem with file:line:key."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path as FsPath
from typing import Any

from abh3_supervisor.config.endpoint import Endpoint, parse_endpoint
from abh3_supervisor.config.faults import check_fault_units, check_fault_wheels, parse_faults
from abh3_supervisor.config.interfaces import SHARED_BY_PROCESSES, unknown_interface
from abh3_supervisor.config.model import (
    MAX_UNITS_PER_TURN,
    STOP_RAMP_S,
    UNITS_PER_TURN,
    BroadcastConfig,
    BusConfig,
    Config,
    ControlMode,
    Limits,
    Role,
    SimConfig,
    UnitConfig,
    VelocityModel,
    VerifyMode,
)
from abh3_supervisor.config.robots import parse_robots, section
from abh3_supervisor.config.simdrives import (
    TAU_MAX_MS,
    check_sim_units,
    parse_forms,
    parse_params,
    parse_startup,
    parse_time_constants,
)
from abh3_supervisor.config.source import Section, Source, load_source, read_text
from abh3_supervisor.core.commands import RESPONSE_OK, parse_command
from abh3_supervisor.core.kinematics import Geometry
from abh3_supervisor.errors import CommandError, ConfigError
from abh3_supervisor.params.telabh3 import DEFAULT_FORMAT, Checksum, TelFormat
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.protocol.ids import MAX_ADDRESS
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY

NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
BITRATES = (250_000, 500_000, 1_000_000)  # what the ABH3 supports (§1)

TOP_KEYS = {"buses", "units", "robots", "plugins", "foxglove", "stop_ramp_s"}
BUS_KEYS = {"interface", "channel", "bitrate", "simulate", "options", "units_per_turn"}
BUS_ARGUMENTS = {"interface", "channel", "bitrate"}  # can.Bus(...) takes them from the bus
SIM_KEYS = {
    "external",
    "command_zero_timeout_ms",
    "error_timeout_ms",
    "accel",
    "time_constant_ms",
    "unit_time_constant_ms",
    "reply_latency_ms",
    "dp0_period_ms",
    "broadcast_period_ms",
    "faults",
    "params",
    "telabh3_form",
    "startup",
}
UNIT_KEYS = {
    "name",
    "bus",
    "abh3_id",
    "host_id",
    "priority",
    "brd_group",
    "protocol",
    "timeout_ms",
    "reply_timeout_ms",
    "drive_timeout_ms",
    "command_rate_hz",
    "control",
    "velocity_model",
    "role",
    "broadcast",
    "geometry",
    "limits",
    "data_select",
    "startup",
    "telabh3",
    "verify",
}
TELABH3_KEYS = {"header", "checksum"}
BROADCAST_KEYS = {"mask", "rate_hz", "listen_only"}
GEOMETRY_KEYS = {"rate_num", "rate_den", "wheel", "width", "pulses_per_rev"}
LIMIT_KEYS = {"velocity", "current"}
SELECT_KEYS = {"ay", "bx"}
# offline (timeout_ms) at most this many drive timeouts: see _timing
OFFLINE_PER_DRIVE_TIMEOUT = 10


def load_config(path: str | FsPath) -> Config:
    """Read and validate a YAML file; raise :class:`ConfigError` listing every problem."""
    return parse_config(read_text(path), str(path))


def parse_config(text: str, file: str = "<config>") -> Config:
    src = load_source(file, text)
    if not isinstance(src.data, dict):
        src.error((), "expected a mapping with buses, units and plugins")
    src.raise_if_problems()  # nothing below means anything without a sound document
    top = Section(src, (), src.data, TOP_KEYS)
    buses = _buses(top)
    units = _units(top, buses)
    check_fault_units(top, buses, units)
    check_sim_units(top, buses, units)
    units = _with_simulated_startup(buses, units)
    robots = parse_robots(top, units, NAME)
    check_fault_wheels(top, buses, units, robots)
    src.unit_names = tuple(units)
    plugins = top.sub("plugins", None)  # each plugin checks its own section's keys
    foxglove = _foxglove(top)
    # the way out's controlled stop: SERVO and brake release kept at most this long while
    # the drives ramp down (docs/safety.md, "Stop categories")
    stop_ramp_s = top.number("stop_ramp_s", STOP_RAMP_S, 0, 10)
    src.raise_if_problems()
    config = Config(
        file=file,
        buses=buses,
        units=units,
        plugins=dict(plugins.items()),
        plugin_lines={name: src.line(("plugins", name)) for name, _ in plugins.items()},
        source=src,
        text=text,
        declared_robots=robots,
        foxglove=foxglove,
        stop_ramp_s=stop_ramp_s,
    )
    _dry_run_startup(src, config)
    src.raise_if_problems()
    return config


def _foxglove(top: Section) -> Endpoint | None:
    if top.data.get("foxglove") is None:
        return None
    try:
        endpoint = parse_endpoint(top.data["foxglove"])
    except ValueError as exc:
        top.error("foxglove", str(exc))
        return None
    where = f"{top.src.file}:{top.src.line(('foxglove',))}: foxglove:"
    return dataclasses.replace(endpoint, where=where)


def _dry_run_startup(src: Source, config: Config) -> None:
    """Run every unit's ``startup:`` on a supervisor that sends nothing: a command that
    would be refused at start (VEL in current control, anything on a monitor unit, VEL
    after TORQUE ON ON) is a mistake in the file, said now rather than logged at start."""
    from abh3_supervisor.core.supervisor import Notice, Supervisor, SupervisorEvent
    from abh3_supervisor.core.verify import State, Verification

    sup = Supervisor(config, clock=lambda: 0.0)
    reasons: list[str] = []

    def keep(event: SupervisorEvent) -> None:
        if isinstance(event, Notice):
            reasons.append(event.message)

    sup.subscribe(keep)
    for state in sup.units.values():  # start-up runs once a unit is verified (or not held)
        state.verify = Verification(State.OK, state.cfg.verify)
    for index, (name, unit) in enumerate(config.units.items()):
        for i, text in enumerate(unit.startup):
            reasons.clear()
            answer = sup.startup(name, text).response  # as the run's startup:<unit> does
            if answer != RESPONSE_OK:
                why = reasons[-1] if reasons else "not a command"
                src.error(
                    _startup_path(config, index, unit, i), f"would be refused at start: {why}"
                )


def _with_simulated_startup(
    buses: dict[str, BusConfig], units: dict[str, UnitConfig]
) -> dict[str, UnitConfig]:
    """Each unit's start-up with its simulated bus's ``simulate.startup`` after its own."""
    out = dict(units)
    for name, unit in units.items():
        sim = buses[unit.bus].simulate if unit.bus in buses else None
        extra = dict(sim.startup).get(name, ()) if sim is not None else ()
        if extra:
            out[name] = dataclasses.replace(unit, startup=unit.startup + extra)
    return out


def _startup_path(config: Config, index: int, unit: UnitConfig, i: int) -> tuple[str | int, ...]:
    """Where start-up command ``i`` of ``unit`` is written: its own, or its bus's."""
    own = len(_own_startup(config, index))
    if i < own:
        return ("units", index, "startup", i)
    return ("buses", unit.bus, "simulate", "startup", unit.name, i - own)


def _own_startup(config: Config, index: int) -> list[object]:
    raw = config.source.data.get("units") if config.source is not None else None
    item = raw[index] if isinstance(raw, list) and index < len(raw) else None
    own = item.get("startup") if isinstance(item, dict) else None
    return own if isinstance(own, list) else []


def _buses(top: Section) -> dict[str, BusConfig]:
    if not top.has("buses"):
        top.error("buses", "missing: declare at least one bus")
        return {}
    raw = top.data["buses"]
    section = Section(
        top.src, ("buses",), raw, {str(k) for k in (raw if isinstance(raw, dict) else {})}
    )
    buses: dict[str, BusConfig] = {}
    for name, _ in section.items():
        if not NAME.match(name):
            section.error(name, "bus names are letters, digits and '_', starting with a letter")
        b = section.sub(name, BUS_KEYS)
        bitrate = b.integer("bitrate", 500_000, 1, 1_000_000)
        if bitrate not in BITRATES:
            b.error(
                "bitrate", f"{bitrate} is not an ABH3 bitrate (allowed: 250000, 500000, 1000000)"
            )
        options = b.sub("options", None)
        for key in BUS_ARGUMENTS & set(options.data):
            options.error(key, f"set {key} on the bus itself, not in its options")
        interface = b.text("interface", "socketcan")
        if b.has("interface") and (problem := unknown_interface(interface)):
            b.error("interface", problem)  # simulated too: the file is meant for the robot
        buses[name] = BusConfig(
            name=name,
            interface=interface,
            channel=_channel(b),
            bitrate=bitrate,
            simulate=_simulate(b, interface),
            options=dict(options.items()),
            units_per_turn=b.integer("units_per_turn", UNITS_PER_TURN, 1, MAX_UNITS_PER_TURN),
        )
    if not buses:
        top.error("buses", "declare at least one bus")
    return buses


def _channel(b: Section) -> str:
    value = b.data.get("channel", "can0")
    # python-can takes a name ("can0", "PCAN_USBBUS1") or a number (kvaser, vector)
    if isinstance(value, bool) or not isinstance(value, str | int) or value == "":
        b.error("channel", f"expected one channel name or number, got {value!r}")
        return "can0"
    return str(value)


def _simulate(b: Section, interface: str) -> SimConfig | None:
    # on an interface made for processes to share, the drives are another process's
    external = interface in SHARED_BY_PROCESSES
    value = b.data.get("simulate", False)
    if value is False:
        return None
    if value is True:
        return SimConfig(external=external)
    if not isinstance(value, dict):  # `simulate:` with no value is a mistake, never "on"
        b.error(
            "simulate", f"expected true, false or a mapping of simulator options, got {value!r}"
        )
        return None
    s = b.sub("simulate", SIM_KEYS)
    d = SimConfig()
    return SimConfig(
        command_zero_timeout_ms=(
            s.integer("command_zero_timeout_ms", 0, 0, 60_000)
            if s.has("command_zero_timeout_ms")
            else d.command_zero_timeout_ms
        ),
        error_timeout_ms=s.integer("error_timeout_ms", d.error_timeout_ms, 0, 60_000),
        accel=s.number("accel", d.accel, 0, 1e6, lo_open=True),
        time_constant_ms=(
            s.number("time_constant_ms", 0.0, 0, TAU_MAX_MS, lo_open=True)
            if s.has("time_constant_ms")
            else d.time_constant_ms
        ),
        unit_time_constant_ms=parse_time_constants(s),
        reply_latency_ms=s.number("reply_latency_ms", d.reply_latency_ms, 0, 10_000),
        dp0_period_ms=s.integer("dp0_period_ms", d.dp0_period_ms, 0, 1000),
        broadcast_period_ms=s.integer("broadcast_period_ms", d.broadcast_period_ms, 0, 1000),
        faults=parse_faults(s),
        params=parse_params(s),
        telabh3_forms=parse_forms(s),
        startup=parse_startup(s),
        external=s.boolean("external", external),
    )


def _units(top: Section, buses: dict[str, BusConfig]) -> dict[str, UnitConfig]:
    raw = top.data.get("units")
    if not isinstance(raw, list) or not raw:
        what = "declare at least one unit" if raw == [] else "expected a list of units"
        top.error("units", f"{what} (each a mapping with at least 'name')")
        return {}
    units: dict[str, UnitConfig] = {}
    addresses: dict[tuple[str, int], str] = {}
    index_of: dict[str, int] = {}
    for i, item in enumerate(raw):
        u = Section(top.src, ("units", i), item, UNIT_KEYS)
        before = len(top.src.problems)
        unit = _unit(u, buses)
        if unit is None:
            continue
        if len(top.src.problems) == before:  # rules over values only once each is sound
            _timing(u, unit)
        if unit.name in units:
            u.error("name", f"duplicate unit name '{unit.name}'")
        elif (unit.bus, unit.abh3_id) in addresses:
            other = addresses[(unit.bus, unit.abh3_id)]
            u.error(
                "abh3_id", f"unit '{other}' already uses abh3_id {unit.abh3_id} on bus '{unit.bus}'"
            )
        units[unit.name] = unit
        index_of.setdefault(unit.name, i)
        addresses.setdefault((unit.bus, unit.abh3_id), unit.name)
    for unit in units.values():
        drive = addresses.get((unit.bus, unit.host_id))
        if drive is not None:
            top.src.error(
                ("units", index_of[unit.name], "host_id"),
                f"host_id {unit.host_id} is the abh3_id of unit '{drive}' on bus '{unit.bus}'",
            )
    return units


def _unit(u: Section, buses: dict[str, BusConfig]) -> UnitConfig | None:
    if not u.has("name"):
        u.error("name", "missing: every unit needs a name")
        return None
    name = u.text("name", "")
    if not name:
        return None
    if not NAME.match(name):
        u.error("name", f"'{name}': unit names are letters, digits and '_', starting with a letter")
    if u.has("bus"):
        bus = u.text("bus", "")
        if bus and bus not in buses:
            u.error(
                "bus", f"'{bus}' is not a declared bus (declared: {', '.join(buses) or 'none'})"
            )
    elif len(buses) == 1:
        bus = next(iter(buses))
    else:
        if buses:  # with none, the missing buses were reported already
            u.error("bus", "missing: several buses are declared, say which one this unit is on")
        bus = ""
    d = UnitConfig(name=name, bus=bus)
    b = u.sub("broadcast", BROADCAST_KEYS)
    g = section(u.src, (*u.path, "geometry"), u.data.get("geometry"), GEOMETRY_KEYS, "wheel")
    lim = u.sub("limits", LIMIT_KEYS)
    sel = u.sub("data_select", SELECT_KEYS)
    tel = u.sub("telabh3", TELABH3_KEYS)
    return UnitConfig(
        name=name,
        bus=bus,
        abh3_id=u.integer("abh3_id", d.abh3_id, 0, MAX_ADDRESS),
        host_id=u.integer("host_id", d.host_id, 0, MAX_ADDRESS),
        priority=u.integer("priority", d.priority, 0, 7),
        brd_group=u.integer("brd_group", d.brd_group, 0, 31),
        protocol=Generation(u.choice("protocol", d.protocol, [g.value for g in Generation])),
        timeout_ms=u.integer("timeout_ms", d.timeout_ms, 1, 60_000),
        reply_timeout_ms=u.integer("reply_timeout_ms", d.reply_timeout_ms, 1, 60_000),
        drive_timeout_ms=u.integer("drive_timeout_ms", d.drive_timeout_ms, 10, 60_000),
        command_rate_hz=u.number("command_rate_hz", d.command_rate_hz, 1, 1000),
        control=ControlMode(u.choice("control", d.control, [m.value for m in ControlMode])),
        velocity_model=VelocityModel(
            u.choice("velocity_model", d.velocity_model, [m.value for m in VelocityModel])
        ),
        role=Role(u.choice("role", d.role, [r.value for r in Role])),
        broadcast=BroadcastConfig(
            mask=b.integer("mask", 0x7F, 0, 0x7F),
            rate_hz=b.number("rate_hz", 10.0, 0.01, 1000),
            listen_only=b.boolean("listen_only", False),
        ),
        geometry=Geometry(
            # lower bounds keep every conversion finite (1e-300 would overflow to inf)
            rate_num=g.number("rate_num", 1.0, 1e-6, 1e6),
            rate_den=g.number("rate_den", 10.0, 1e-6, 1e6),
            wheel=g.number("wheel", 0.1, 0.001, 100),
            width=g.number("width", 0.5, 0.001, 100),
            pulses_per_rev=g.number("pulses_per_rev", 0.0, 0, 1e9),
        ),
        limits=Limits(
            velocity=lim.number("velocity", VELOCITY.largest, 0, VELOCITY.largest, lo_open=True),
            current=lim.number("current", CURRENT.largest, 0, CURRENT.largest, lo_open=True),
        ),
        data_select=(sel.integer("ay", 7, 0, 7), sel.integer("bx", 7, 0, 7)),
        startup=_startup(u),
        telabh3=TelFormat(
            header=tel.boolean("header", DEFAULT_FORMAT.header),
            checksum=Checksum(
                tel.choice("checksum", DEFAULT_FORMAT.checksum, [c.value for c in Checksum])
            ),
        )
        if u.has("telabh3")
        else None,  # found by the first exchange (params/session.py)
        verify=_verify(u),
    )


def _verify(u: Section) -> VerifyMode:
    if u.data.get("verify") is False:  # YAML 1.1 reads a bare `off` as false
        return VerifyMode.OFF
    return VerifyMode(u.choice("verify", VerifyMode.WARN, [m.value for m in VerifyMode]))


def _timing(u: Section, unit: UnitConfig) -> None:
    """Rules that keep a drive alive and make "offline" mean silent (docs: Timing rules)."""
    period = 1000 / unit.command_rate_hz  # ms between DP0 exchanges
    drive, reply, offline = unit.drive_timeout_ms, unit.reply_timeout_ms, unit.timeout_ms
    if unit.role is Role.COMMAND:
        if period >= drive / 2:
            _rule(
                u,
                ("command_rate_hz", "drive_timeout_ms"),
                f"{unit.command_rate_hz:g} Hz sends a command every {period:g} ms: not under "
                f"half of drive_timeout_ms {drive} (the drive stops itself after that long "
                f"without one); use more than {2000 / drive:g} Hz",
            )
        if reply >= drive:
            _rule(
                u,
                ("reply_timeout_ms", "drive_timeout_ms"),
                f"{reply} ms is not below drive_timeout_ms {drive}: waiting that long for a "
                "lost reply holds the next command back until the drive has stopped itself",
            )
        if offline > OFFLINE_PER_DRIVE_TIMEOUT * drive:
            _rule(
                u,
                ("timeout_ms", "drive_timeout_ms"),
                f"{offline} ms is more than {OFFLINE_PER_DRIVE_TIMEOUT} × drive_timeout_ms "
                f"{drive}: a drive silent that long has stopped itself yet would count as "
                "online and get its last command again when it answers; use at most "
                f"{OFFLINE_PER_DRIVE_TIMEOUT * drive} ms",
            )
    shortest = 2 * max(period, reply)
    if offline < shortest:
        _rule(
            u,
            ("timeout_ms", "reply_timeout_ms", "command_rate_hz"),
            f"{offline} ms would take the unit offline after one lost reply: use at least "
            f"{shortest:g} ms (twice the longer of the command period {period:g} ms and "
            f"reply_timeout_ms {reply})",
        )


def _rule(u: Section, keys: tuple[str, ...], message: str) -> None:
    """Report on the first key, at the line of the first of ``keys`` the file sets."""
    written = [key for key in keys if u.has(key)]
    line = u.src.line((*u.path, written[0])) if written else None
    u.src.error((*u.path, keys[0]), message, line)


def _startup(u: Section) -> tuple[str, ...]:
    raw: Any = u.data.get("startup", [])
    if not isinstance(raw, list) or not all(isinstance(c, str) for c in raw):
        u.error("startup", "expected a list of command strings, e.g. ['SERVO ON ON']")
        return ()
    for i, command in enumerate(raw):
        try:
            parse_command(command)
        except CommandError as exc:
            u.src.error((*u.path, "startup", i), f"{command!r}: {exc}")
    return tuple(raw)


__all__ = ["ConfigError", "load_config", "parse_config"]
