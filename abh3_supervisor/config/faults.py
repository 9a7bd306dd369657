"""``simulate.faults``: scripted faults of the built-in simulator, to rehearse them."""

from __future__ import annotations

import math
from collections.abc import Mapping

from abh3_supervisor.config.model import (
    AXIS_KINDS,
    BUILT_KINDS,
    WIRING_KINDS,
    BusConfig,
    Fault,
    FaultKind,
    Role,
    UnitConfig,
)
from abh3_supervisor.config.source import Section
from abh3_supervisor.core.robot import RobotConfig
from abh3_supervisor.errors import did_you_mean

FAULT_KEYS = {"kind", "at_s", "for_s", "unit", "bits", "delay_ms", "axis", "factor", "other"}
KIND_KEYS = {  # what each kind reads besides kind, at_s, for_s and unit
    FaultKind.ERROR_BITS: {"bits"},
    FaultKind.SLOW_REPLIES: {"delay_ms"},
    FaultKind.TP_SLOW_DT: {"delay_ms"},
    FaultKind.REVERSED_AXIS: {"axis"},
    FaultKind.SCALE: {"axis", "factor"},
    FaultKind.NO_ENCODER: {"axis"},
    FaultKind.MIRRORED_WHEEL: {"axis"},
    FaultKind.SWAPPED_DRIVES: {"other"},
    FaultKind.WRONG_TRACK: {"factor"},
    FaultKind.WRONG_DIAMETER: {"factor"},
}
# what a wiring kind cannot do without (the others have defaults)
REQUIRED = {k: KIND_KEYS[k] for k in AXIS_KINDS} | {
    FaultKind.SWAPPED_DRIVES: {"unit", "other"},
    FaultKind.WRONG_TRACK: {"factor"},
    FaultKind.WRONG_DIAMETER: {"factor"},
}
AXES = ("A", "B")
MAX_S = 7 * 86400.0


def parse_faults(sim: Section) -> tuple[Fault, ...]:
    if not sim.has("faults"):
        return ()
    raw = sim.data["faults"]
    if not isinstance(raw, list):
        sim.error("faults", "expected a list of faults, e.g. [{kind: silent, at_s: 2, for_s: 1}]")
        return ()
    faults = []
    for i, item in enumerate(raw):
        f = Section(sim.src, (*sim.path, "faults", i), item, FAULT_KEYS)
        if not f.has("kind"):
            f.error("kind", f"missing (one of: {_kinds()})")
            continue
        named = f.data["kind"]
        if str(named) not in {k.value for k in FaultKind}:
            did = did_you_mean(str(named), [k.value for k in FaultKind])
            f.error("kind", f"{named!r} is not one of: {_kinds()}{did}")
            continue  # what else it says depends on the kind: nothing more to judge
        kind = FaultKind(str(named))
        for key in FAULT_KEYS - {"kind", "at_s", "for_s", "unit"} - KIND_KEYS.get(kind, set()):
            if f.has(key):
                f.error(key, f"does not apply to kind {kind.value}")
        wiring = kind in WIRING_KINDS  # from the start, for ever, unless timed
        for key in ("at_s", "for_s") if kind in BUILT_KINDS else ():
            if f.has(key):
                f.error(key, f"does not apply to kind {kind.value}: how it is built, for ever")
        for key in ("at_s", "for_s") if not wiring else ():
            if not f.has(key):
                f.error(key, "missing: when the fault starts and how long it lasts [s]")
        for key in sorted(REQUIRED.get(kind, set())):
            if not f.has(key):
                f.error(key, f"missing: {kind.value} needs it ({_needs(key, kind)})")
        unit = f.text("unit", "") or None
        if unit is not None and kind is FaultKind.BUS_SEND_ERROR:
            f.error("unit", "bus_send_error is a fault of the whole bus: no unit")
        faults.append(
            Fault(
                kind=kind,
                at_s=f.number("at_s", 0.0, 0.0, MAX_S),
                for_s=(
                    f.number("for_s", 1.0, 0.0, MAX_S, lo_open=True)
                    if f.has("for_s") or not wiring
                    else math.inf
                ),
                unit=unit,
                bits=f.integer("bits", Fault.bits, 1, 0xFFFFFFFF),
                delay_ms=f.number("delay_ms", Fault.delay_ms, 0.0, 10_000.0, lo_open=True),
                axis=AXES.index(f.choice("axis", "A", list(AXES))),
                factor=f.number("factor", 1.0, 0.0, 100.0, lo_open=True),
                other=f.text("other", "") or None,
            )
        )
    return tuple(faults)


def _kinds() -> str:
    return ", ".join(k.value for k in FaultKind)


def _needs(key: str, kind: FaultKind) -> str:
    if key == "axis":
        return "the motor: A or B"
    if key in ("unit", "other"):
        return "the two units whose drives sit on each other's wheels: unit: X, other: Y"
    if kind is FaultKind.WRONG_TRACK:
        return "the true track over the file's track_m, e.g. 1.2"
    if kind is FaultKind.WRONG_DIAMETER:
        return "the true wheel diameter over the file's diameter_m, e.g. 0.5 (a radius)"
    return "pulses counted per pulse the file's geometry expects, e.g. 1.1"


def check_fault_units(
    top: Section, buses: dict[str, BusConfig], units: dict[str, UnitConfig]
) -> None:
    """A fault naming a unit (or an ``other`` one) must name one simulated on that bus."""
    for name, bus in buses.items():
        for i, fault in enumerate(bus.simulate.faults if bus.simulate else ()):
            for key, named in (("unit", fault.unit), ("other", fault.other)):
                unit = units.get(named) if named is not None else None
                if named is not None and (unit is None or unit.bus != name):
                    here = [u.name for u in units.values() if u.bus == name]
                    top.src.error(
                        ("buses", name, "simulate", "faults", i, key),
                        f"no unit '{named}' on bus {name} (units there: {', '.join(here)})",
                    )
            if fault.other is not None and fault.other == fault.unit:
                top.src.error(
                    ("buses", name, "simulate", "faults", i, "other"),
                    "swapped_drives swaps two different units",
                )


# robot faults that need a commanded unit (a monitor is never commanded, no wheel of it)
COMMANDED_KINDS = {FaultKind.SWAPPED_DRIVES, FaultKind.WRONG_PROTOCOL, FaultKind.MIRRORED_WHEEL}


def check_fault_wheels(
    top: Section,
    buses: dict[str, BusConfig],
    units: dict[str, UnitConfig],
    robots: Mapping[str, RobotConfig],
) -> None:
    """A robot fault must be on a commanded unit, and ``mirrored_wheel`` on an axis that is
    a wheel (of the declared robot of the unit; a unit of no declared robot is a one-drive
    robot of its own, both axes wheels)."""
    wheel_of = {(w.unit, w.axis): r for r in robots.values() for w in r.wheels}
    robot_of = {u: r for r in robots.values() for u in r.units}
    for name, bus in buses.items():
        for i, fault in enumerate(bus.simulate.faults if bus.simulate else ()):
            if fault.kind not in COMMANDED_KINDS:
                continue
            at = ("buses", name, "simulate", "faults", i)
            for key, named in (("unit", fault.unit), ("other", fault.other)):
                unit = units.get(named) if named is not None else None
                if unit is not None and unit.role is Role.MONITOR:
                    top.src.error(
                        (*at, key),
                        f"unit '{named}' is a monitor (never commanded, no robot's wheel): "
                        f"{fault.kind.value} needs a commanded unit",
                    )
            robot = robot_of.get(fault.unit) if fault.unit is not None else None
            if (
                fault.kind is FaultKind.MIRRORED_WHEEL
                and robot is not None
                and (fault.unit, fault.axis) not in wheel_of
            ):
                axes = [AXES[w.axis] for w in robot.wheels if w.unit == fault.unit]
                top.src.error(
                    (*at, "axis"),
                    f"axis {AXES[fault.axis]} of unit '{fault.unit}' is no wheel of robot "
                    f"'{robot.name}' (its wheels on {fault.unit}: axis {', '.join(axes)})",
                )
