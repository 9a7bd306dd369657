"""Bus-load plan: what the configured schedule puts on each bus, before anything runs."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from abh3_supervisor.config.model import Config, Role, UnitConfig
from abh3_supervisor.wire import worst_case_bits

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


@dataclass(frozen=True)
class BusPlan:
    bus: str
    bitrate: int
    units: list[UnitLoad]
    frames_per_s: float
    bits_per_s: float
    load_percent: float
    warning: str | None

    def to_json(self) -> dict[str, object]:
        return asdict(self)


def unit_load(u: UnitConfig) -> UnitLoad:
    request = DP0 if u.role is Role.COMMAND else REQUEST  # a monitor asks with the request PGN
    polls = 0.0 if u.broadcast.listen_only or not u.broadcast.mask else u.broadcast.rate_hz
    bits = u.command_rate_hz * (request + DP0) + polls * (REQUEST + DP0)
    return UnitLoad(u.name, u.command_rate_hz, polls, 2 * (u.command_rate_hz + polls), bits)


def plan(config: Config) -> list[BusPlan]:
    plans = []
    for name, bus in config.buses.items():
        units = [unit_load(u) for u in config.units_on(name)]
        bits = sum(u.bits_per_s for u in units)
        percent = 100 * bits / bus.bitrate
        warning = None
        if percent > 100:
            warning = (
                f"planned load {percent:.1f} % exceeds the bus: lower rates or raise the bitrate"
            )
        elif percent > WARN_PERCENT:
            warning = f"planned load {percent:.1f} % is above {WARN_PERCENT:.0f} %: little headroom"
        plans.append(
            BusPlan(
                name, bus.bitrate, units, sum(u.frames_per_s for u in units), bits, percent, warning
            )
        )
    return plans
