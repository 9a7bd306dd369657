"""What the screens show, computed from the Supervisor without any Textual: testable alone."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from abh3_supervisor.config.model import VelocityModel
from abh3_supervisor.planner import BusPlan
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.runtime import Runtime
from abh3_supervisor.supervisor import Supervisor

HISTORY = 200  # samples kept for the plots: 20 s at the 10 Hz refresh


@dataclass
class Trace:
    cmd: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    fbk: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    current: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))
    load: deque[float] = field(default_factory=lambda: deque(maxlen=HISTORY))


def onoff(value: bool) -> str:
    return "ON" if value else "off"


def pair(word: int, ay: int, bx: int) -> str:
    return f"{onoff(bool(word & ay))}/{onoff(bool(word & bx))}"


def fmt(value: float | None, digits: int = 1) -> str:
    return "–" if value is None else f"{value + 0.0:.{digits}f}"


def overview_row(sup: Supervisor, name: str) -> dict[str, str]:
    unit = sup.units[name]
    slot = sup.schedulers[unit.cfg.bus].slots[name]
    now = sup.clock()
    control = unit.words.get("control", unit.inputs)
    fb = unit.feedback
    status = {True: "online", False: "OFFLINE", None: "waiting"}[unit.online]
    brd3 = unit.status.get(3, (0.0, None))[1]
    brd5 = unit.status.get(5, (0.0, None))[1]
    error, alarm = unit.words.get("error", 0), unit.words.get("alarm", 0)
    return {
        "unit": name,
        "state": status,
        "proto": unit.cfg.protocol.value,
        "mode": f"{unit.setpoint.kind.value}/{unit.cfg.velocity_model.value}",
        "servo": pair(control, *unit.layout.servo),
        "start": pair(control, *unit.layout.start),
        "cmd": f"{fmt(unit.setpoint.ay)} {fmt(unit.setpoint.bx)}",
        "fbk A/B": f"{fmt(fb.vel_a if fb else None)} {fmt(fb.vel_b if fb else None)}",
        "fbk Y/X": f"{fmt(fb.vel_y if fb else None)} {fmt(fb.vel_x if fb else None)}",
        "current %": (
            f"{fmt(brd3.cur_cmd_ay)} {fmt(brd3.cur_cmd_bx)}"
            if isinstance(brd3, frames.Brd3)
            else "–"
        ),
        "load %": (
            f"{fmt(brd3.load_a, 0)} {fmt(brd3.load_b, 0)}" if isinstance(brd3, frames.Brd3) else "–"
        ),
        "supply V": (
            f"{fmt(brd5.main_volt)} {fmt(brd5.control_volt)}"
            if isinstance(brd5, frames.Brd5)
            else "–"
        ),
        "errors": " ".join(flags.FAULT.names(error)) or "–",
        "alarms": " ".join(flags.FAULT.names(alarm)) or "–",
        "rate Hz": f"{slot.stats.achieved_rate_hz(now):.1f}/{slot.stats.requested_rate_hz:g}",
    }


COLUMNS = [
    "unit",
    "state",
    "proto",
    "mode",
    "servo",
    "start",
    "cmd",
    "fbk A/B",
    "fbk Y/X",
    "current %",
    "load %",
    "supply V",
    "errors",
    "alarms",
    "rate Hz",
]


def flag_lines(layout: flags.Layout, word_name: str, value: int | None) -> list[tuple[bool, str]]:
    """Every bit of a word in the unit's generation, set or not: (set, "bit name")."""
    word = layout.words[word_name]
    value = value or 0
    return [(bool(value & b.mask), f"{b.bit:>2} {b.name}") for b in word.bits]


def detail_lines(sup: Supervisor, name: str) -> list[str]:
    unit = sup.units[name]
    slot = sup.schedulers[unit.cfg.bus].slots[name]
    st = slot.stats
    lines = [
        f"unit {name}: abh3_id {unit.cfg.abh3_id}, host {unit.cfg.host_id}, "
        f"bus {unit.cfg.bus}, group {unit.cfg.brd_group}, protocol {unit.cfg.protocol}",
        f"exchanges {st.replies}/{st.commands_sent}, timeouts {st.timeouts}, "
        f"send errors {st.send_errors}, rtt p50 {fmt(st.rtt_ms(50), 2)} ms, "
        f"p99 {fmt(st.rtt_ms(99), 2)} ms, status packets {st.broadcasts}, "
        f"malformed {st.malformed}, gaps {st.gaps}",
    ]
    status = {n: r for n, (_, r) in dict(unit.status).items()}  # copy: another thread writes
    b4, b5, b6 = status.get(4), status.get(5), status.get(6)
    if isinstance(b4, frames.Brd4):
        lines.append(f"pulses A {b4.pulse_a}  B {b4.pulse_b}")
    if isinstance(b5, frames.Brd5):
        lines.append(
            f"analog0 {b5.analog0:.2f} V  analog1 {b5.analog1:.2f} V  "
            f"main {b5.main_volt:.1f} V  control {b5.control_volt:.1f} V"
        )
    if isinstance(b6, frames.Brd6):
        lines.append(f"monitor0 {b6.monitor0:.4f}  monitor1 {b6.monitor1:.4f}")
    return lines


class Sampler:
    """Keeps the recent history the plots draw, one sample per refresh."""

    def __init__(self, sup: Supervisor) -> None:
        self.sup = sup
        self.traces = {name: Trace() for name in sup.units}

    def sample(self) -> None:
        for name, unit in self.sup.units.items():
            trace = self.traces[name]
            fb = unit.feedback
            travel = unit.cfg.velocity_model is VelocityModel.TRAVEL
            trace.cmd.append(unit.setpoint.ay)
            trace.fbk.append((fb.vel_y if travel else fb.vel_a) if fb else 0.0)
            brd3 = unit.status.get(3, (0.0, None))[1]
            if isinstance(brd3, frames.Brd3):
                trace.current.append(brd3.cur_cmd_ay)
                trace.load.append(brd3.load_a)


@dataclass
class BusSample:
    frames: int = 0
    t: float = 0.0


def bus_lines(rt: Runtime, plans: dict[str, BusPlan], last: dict[str, BusSample]) -> list[str]:
    """Frames/s, estimated load % and error counts per bus since the previous call."""
    lines = []
    for name, pump in rt.pumps.items():
        now = rt.supervisor.clock()
        total = pump.frames_sent + pump.frames_received
        prev = last.get(name, BusSample(total, now))
        rate = (total - prev.frames) / (now - prev.t) if now > prev.t else 0.0
        last[name] = BusSample(total, now)
        p = plans[name]
        bits_per_frame = p.bits_per_s / p.frames_per_s if p.frames_per_s else 0.0
        load = 100 * rate * bits_per_frame / p.bitrate
        lines.append(
            f"bus {name}: {rate:7.0f} frames/s  ≈{load:5.1f} % of {p.bitrate} bit/s "
            f"(planned {p.load_percent:.1f} %)  send errors {pump.send_errors}  "
            f"bus errors {pump.bus_errors}"
        )
        for unit, slot in rt.supervisor.schedulers[name].slots.items():
            st = slot.stats
            lines.append(
                f"    {unit:<12} timeouts {st.timeouts:<6} send errors "
                f"{st.send_errors:<4} replies {st.replies:<8} status {st.broadcasts:<8} "
                f"malformed {st.malformed:<4} gaps {st.gaps}"
            )
    return lines
