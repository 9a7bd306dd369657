"""``simulate.params``, ``simulate.telabh3_form``, ``simulate.unit_time_constant_ms`` and
``simulate.startup``: simulated drives set up otherwise than the file says, to rehearse
what `verify` and the TelABH3 form probe report, answering with a time constant of their
own, or commanded at start only while simulated.

The simulated drives' parameter tables follow the file (their unit's ``abh3_id``,
``host_id``, ``brd_group``, ``drive_timeout_ms`` and the bus's bitrate, simulator/bus.py);
``params`` overrides single words per unit, given as values of the address's kind
(docs/parameters.md). ``telabh3_form`` limits the string forms a unit's drive reads.
"""

from __future__ import annotations

import math
from typing import Any

from abh3_supervisor.config.model import BusConfig, UnitConfig
from abh3_supervisor.config.source import EXPONENT_ONLY, Section
from abh3_supervisor.core.commands import parse_command
from abh3_supervisor.errors import CodecError, CommandError
from abh3_supervisor.params import table
from abh3_supervisor.params.telabh3 import DEFAULT_FORMAT, Checksum, TelFormat

FORM_KEYS = {"header", "checksum"}
TAU_MAX_MS = 60_000.0
ANY, NONE = "any", "none"


def parse_params(sim: Section) -> tuple[tuple[str, tuple[tuple[int, int], ...]], ...]:
    """``params: {UNIT: {ADDRESS: VALUE}}``: each value as the drive's word."""
    if not sim.has("params"):
        return ()
    units = sim.sub("params", None)
    out: list[tuple[str, tuple[tuple[int, int], ...]]] = []
    for unit, raw in units.items():
        where = (*units.path, unit)
        if not isinstance(raw, dict) or not raw:
            sim.src.error(where, "expected a mapping of address → value, e.g. {0x4117: 750}")
            continue
        words: dict[int, int] = {}
        for key, value in raw.items():
            here = (*where, str(key))
            address = _address(key)
            if isinstance(address, str):
                sim.src.error(here, address)
                continue
            word = _word(address, value)
            if isinstance(word, str):
                sim.src.error(here, f"0x{address:04X} {table.label(address)}: {word}")
                continue
            words[address] = word
        out.append((unit, tuple(words.items())))
    return tuple(out)


def parse_startup(sim: Section) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """``startup: {UNIT: [commands]}``: run at start after the unit's own ``startup:``,
    only while this bus is simulated (the demos' motion: a real bus never runs it)."""
    if not sim.has("startup"):
        return ()
    units = sim.sub("startup", None)
    out = []
    for unit, raw in units.items():
        if not isinstance(raw, list) or not all(isinstance(c, str) for c in raw):
            units.error(unit, "expected a list of command strings, e.g. ['SERVO ON ON']")
            continue
        for i, command in enumerate(raw):
            try:
                parse_command(command)
            except CommandError as exc:
                sim.src.error((*units.path, unit, i), f"{command!r}: {exc}")
        out.append((unit, tuple(raw)))
    return tuple(out)


def parse_time_constants(sim: Section) -> tuple[tuple[str, float], ...]:
    """``unit_time_constant_ms: {UNIT: MS}``: that unit's drive's own time constant."""
    if not sim.has("unit_time_constant_ms"):
        return ()
    units = sim.sub("unit_time_constant_ms", None)
    return tuple(
        (unit, units.number(unit, 0.0, 0.0, TAU_MAX_MS, lo_open=True)) for unit, _ in units.items()
    )


def _address(key: Any) -> int | str:
    """The address of a key (a name of the table, 0x hex, or a number), or the problem."""
    if isinstance(key, bool):
        return f"{key!r} is no address: a name of the parameter table or hex (0x4117)"
    if isinstance(key, int):
        ok = 0 <= key <= 0xFFFF
        return key if ok else f"address {key:#x} is not 0x0000-0xFFFF"
    try:
        return table.parse_address(str(key))
    except CodecError as exc:
        return str(exc)


def _word(address: int, value: Any) -> int | str:
    if isinstance(value, str) and EXPONENT_ONLY.match(value):
        return f"YAML reads {value} as text: write it with a dot and a signed exponent"
    if isinstance(value, bool) or not isinstance(value, int | float):
        return f"expected a number (the value, e.g. 750), got {value!r}"
    if not math.isfinite(value):
        return f"{value} is not a finite number"
    try:
        return table.to_word(float(value), table.kind_of(address))
    except CodecError as exc:
        return str(exc)


def parse_forms(sim: Section) -> tuple[tuple[str, tuple[TelFormat, ...]], ...]:
    """``telabh3_form: {UNIT: FORM}``: FORM is ``{header: …, checksum: …}`` (the only form
    that drive reads), ``none`` (it reads none) or ``any`` (the default)."""
    if not sim.has("telabh3_form"):
        return ()
    units = sim.sub("telabh3_form", None)
    out: list[tuple[str, tuple[TelFormat, ...]]] = []
    for unit, raw in units.items():
        if raw == NONE:
            out.append((unit, ()))
        elif raw == ANY:
            continue
        elif isinstance(raw, dict):
            f = units.sub(unit, FORM_KEYS)
            fmt = TelFormat(
                header=f.boolean("header", DEFAULT_FORMAT.header),
                checksum=Checksum(
                    f.choice("checksum", DEFAULT_FORMAT.checksum, [c.value for c in Checksum])
                ),
            )
            out.append((unit, (fmt,)))
        else:
            units.error(
                unit,
                f"expected {{header: …, checksum: …}} (the one form this drive reads), "
                f"'{NONE}' or '{ANY}', got {raw!r}",
            )
    return tuple(out)


def _raw(data: Any, *keys: str) -> dict[Any, Any]:
    for key in keys:
        data = data.get(key) if isinstance(data, dict) else None
    return data if isinstance(data, dict) else {}


def check_sim_units(
    top: Section, buses: dict[str, BusConfig], units: dict[str, UnitConfig]
) -> None:
    """``params``, ``telabh3_form`` and ``unit_time_constant_ms`` must name units simulated
    on that bus."""
    for name, bus in buses.items():
        sim = bus.simulate
        if sim is None:
            continue
        here = [u.name for u in units.values() if u.bus == name]
        named = [("params", unit) for unit, _ in sim.params]
        named += [("telabh3_form", unit) for unit, _ in sim.telabh3_forms]
        named += [("unit_time_constant_ms", unit) for unit, _ in sim.unit_time_constant_ms]
        named += [("startup", unit) for unit, _ in sim.startup]
        forms = _raw(top.data, "buses", name, "simulate", "telabh3_form")
        named += [("telabh3_form", str(u)) for u in forms]  # also those that read `any`
        for key, unit in dict.fromkeys(named):
            if unit not in here:
                top.src.error(
                    ("buses", name, "simulate", key, unit),
                    f"no unit '{unit}' on bus {name} (units there: {', '.join(here)})",
                )
