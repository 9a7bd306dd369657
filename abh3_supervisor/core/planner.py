"""Bus-load plan: what the configured schedule puts on each bus, before anything runs.

Two figures per bus: *expected*, from the exact stuffed length of the frames the schedule
sends with idle payloads (the identifiers are known exactly; zero commands and flags are
what an idle drive exchanges), and *worst case*, with every frame maximally stuffed.
The warning uses the worst case.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from abh3_supervisor.config.model import Config, ControlMode, Role, UnitConfig
from abh3_supervisor.core.wire import exact_bits, worst_case_bits
from abh3_supervisor.protocol import flags, frames, ids

# Keep planned load at or below 70 %: queueing delay for the lowest-priority frame grows
# steeply as a CAN bus nears saturation, and the plan cannot see frames the drives send
# periodically on their own, retransmissions after bus errors or other nodes' traffic.
WARN_PERCENT = 70.0
DP0 = worst_case_bits(8)
REQUEST = worst_case_bits(3)


@dataclass(frozen=True)
class UnitLoad:
    unit: str
    exchanges_per_s: float
    polls_per_s: float
    frames_per_s: float
    bits_per_s: float
    worst_bits_per_s: float


@dataclass(frozen=True)
class BusPlan:
    bus: str
    bitrate: int
    units: list[UnitLoad]
    frames_per_s: float
    bits_per_s: float
    load_percent: float
    worst_load_percent: float
    warning: str | None

    def to_json(self) -> dict[str, object]:
        return asdict(self)


def _expected_bits(u: UnitConfig) -> tuple[float, float]:
    """Exact bits of one DP0 exchange and of one average status poll, idle payloads."""
    zero8 = bytes(8)
    if u.role is Role.COMMAND:
        current = u.control is ControlMode.CURRENT
        inputs = flags.layout(u.protocol).idle(*u.data_select, torque=current)
        request = exact_bits(
            ids.dp0_command_id(u.abh3_id, u.host_id, u.priority),
            frames.encode_dp0_command(0, 0, inputs),
        )
    else:
        request = exact_bits(
            ids.request_id(u.abh3_id, u.host_id, u.priority), frames.encode_request(frames.PGN_DP0)
        )
    exchange = request + exact_bits(ids.dp0_reply_id(u.abh3_id, u.host_id), zero8)
    packets = u.broadcast.packets or (0,)
    poll = sum(
        exact_bits(
            ids.request_id(u.abh3_id, u.host_id, u.priority),
            frames.encode_request(frames.broadcast_pgn(u.brd_group, n)),
        )
        + exact_bits(ids.broadcast_id(u.abh3_id, u.brd_group, n), zero8)
        for n in packets
    ) / len(packets)
    return exchange, poll


def unit_load(u: UnitConfig) -> UnitLoad:
    worst_request = DP0 if u.role is Role.COMMAND else REQUEST
    polls = 0.0 if u.broadcast.listen_only or not u.broadcast.mask else u.broadcast.rate_hz
    exchange, poll = _expected_bits(u)
    return UnitLoad(
        u.name,
        u.command_rate_hz,
        polls,
        2 * (u.command_rate_hz + polls),
        u.command_rate_hz * exchange + polls * poll,
        u.command_rate_hz * (worst_request + DP0) + polls * (REQUEST + DP0),
    )


def plan(config: Config) -> list[BusPlan]:
    plans = []
    for name, bus in config.buses.items():
        units = [unit_load(u) for u in config.units_on(name)]
        bits = sum(u.bits_per_s for u in units)
        worst = 100 * sum(u.worst_bits_per_s for u in units) / bus.bitrate
        warning = None
        if worst > 100:
            warning = (
                f"worst-case load {worst:.1f} % exceeds the bus: lower rates or raise the bitrate"
            )
        elif worst > WARN_PERCENT:
            warning = (
                f"worst-case load {worst:.1f} % is above {WARN_PERCENT:.0f} %: little headroom"
            )
        plans.append(
            BusPlan(
                name,
                bus.bitrate,
                units,
                sum(u.frames_per_s for u in units),
                bits,
                100 * bits / bus.bitrate,
                worst,
                warning,
            )
        )
    return plans


def overloads(config: Config, plans: list[BusPlan]) -> list[str]:
    """A bus planned above 100 %: ``abh3 check`` fails on it and ``abh3 run`` refuses it.

    No ``--force``: the plan follows from the file alone, so the fix is always there (lower
    rates or a higher bitrate), and on an overloaded bus the lowest-priority drives miss
    their keepalive and stop themselves at random.
    """
    out = []
    for p in plans:
        if p.worst_load_percent > 100:
            line = config.source.line(("buses", p.bus)) if config.source else 1
            out.append(
                f"{config.file}:{line}: buses.{p.bus}: worst-case load "
                f"{p.worst_load_percent:.1f} % exceeds the bus at {p.bitrate} bit/s: lower "
                "command_rate_hz or broadcast.rate_hz, or raise the bitrate"
            )
    return out
