"""What a client knows of a running supervisor: its configuration (rebuilt from the YAML
it serves, so typed exactly as the service's) and the last state it pushed.

The TUI renders from a :class:`Mirror` only, never from the service's objects, so it is
the same whether the service runs in another process or a test's fake time feeds it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from abh3_supervisor.config import Config, ControlMode, UnitConfig, parse_config
from abh3_supervisor.core.state import Feedback, Setpoint
from abh3_supervisor.errors import RunError
from abh3_supervisor.protocol import flags, frames

PACKETS: dict[int, type[frames.Broadcast]] = {
    0: frames.Brd0,
    1: frames.Brd1,
    2: frames.Brd2,
    3: frames.Brd3,
    4: frames.Brd4,
    5: frames.Brd5,
    6: frames.Brd6,
}


@dataclass
class Stats:
    """A unit's exchange figures as the service computed them."""

    rate_hz: float = 0.0
    requested_rate_hz: float = 0.0
    replies: int = 0
    commands_sent: int = 0
    broadcasts: int = 0
    timeouts: int = 0
    send_errors: int = 0
    malformed: int = 0
    gaps: int = 0
    rtt_p50_ms: float | None = None
    rtt_p99_ms: float | None = None


@dataclass
class UnitView:
    """One unit as last reported: the fields of the core's ``UnitState`` a client shows."""

    cfg: UnitConfig
    inputs: int
    setpoint: Setpoint
    layout: flags.Layout
    feedback: Feedback | None = None
    status: dict[int, frames.Broadcast] = field(default_factory=dict)
    online: bool | None = None
    words: dict[str, int] = field(default_factory=dict)
    stats: Stats = field(default_factory=Stats)
    verify: dict[str, Any] | None = None  # the drive's settings against the YAML, as sent
    foreign: dict[str, Any] | None = None  # other hosts on its drive (core/foreign.py)
    identified: str | None = None  # the generation its replies show; None: not yet

    @property
    def other_generation(self) -> str | None:
        """Why it is held for answering in the other layout than the file's, or None."""
        if self.identified in (None, str(self.cfg.protocol)):
            return None
        return (
            f"it answers as a {self.identified} drive, the file says protocol: "
            f'"{self.cfg.protocol}": held at a word safe in both generations'
        )

    @property
    def name(self) -> str:
        return self.cfg.name

    @classmethod
    def initial(cls, cfg: UnitConfig) -> UnitView:
        layout = flags.layout(cfg.protocol)
        current = cfg.control is ControlMode.CURRENT
        inputs = layout.idle(*cfg.data_select, torque=current)
        return cls(cfg, inputs, Setpoint(kind=cfg.control), layout)


@dataclass
class BusView:
    frames_sent: int = 0
    frames_received: int = 0
    send_errors: int = 0
    bus_errors: int = 0
    simulated: bool = False
    state: str = "ok"  # as the interface reports it: ok, bus-off, error-passive, …
    since: float = 0.0
    detail: str = ""


@dataclass
class Mirror:
    config: Config
    units: dict[str, UnitView]
    buses: dict[str, BusView]
    t: float = 0.0
    estop: bool = False
    stopping: bool = False
    # the pushes give way to late buses: {"by": n, "late_ms": …}, none at the rate asked
    slowed: dict[str, Any] | None = None
    # each robot and why it may not move (None: every drive of it reports ready); the
    # service's robot decision, as pushed (docs/safety.md); empty before the first state
    robots: dict[str, str | None] = field(default_factory=dict)

    @classmethod
    def of(cls, config: Config, simulated: list[str] | tuple[str, ...] = ()) -> Mirror:
        units = {name: UnitView.initial(cfg) for name, cfg in config.units.items()}
        buses = {name: BusView(simulated=name in simulated) for name in config.buses}
        return cls(config, units, buses)

    @classmethod
    def from_hello(cls, hello: dict[str, Any]) -> Mirror:
        """The service's own configuration, parsed as it parsed it."""
        if not hello.get("config_text"):
            raise RunError(f"the supervisor at {hello.get('config')} sent no configuration text")
        config = parse_config(hello["config_text"], hello["config"])
        return cls.of(config, hello.get("simulated", ()))

    def apply(self, state: dict[str, Any]) -> bool:
        """Take a ``state`` (the method's result, or its notification) if it is newer than
        the one held: a service may send one state twice (it shares an encoded state for a
        few ms), and the copy must not undo what a reply said since (an e-stop confirmed)."""
        if state["t"] <= self.t:
            return False
        self.t, self.estop = state["t"], state["estop"]
        self.stopping = state.get("stopping", False)
        self.slowed = state.get("slowed")
        self.robots = dict(state.get("robots") or {})
        for name, data in state["units"].items():
            if name in self.units:
                _apply_unit(self.units[name], data)
        for name, data in state["buses"].items():
            if name in self.buses:
                _take(self.buses[name], data)
        return True


def _apply_unit(unit: UnitView, data: dict[str, Any]) -> None:
    unit.online = data["online"]
    sp = data["setpoint"]
    unit.setpoint = Setpoint(sp["ay"], sp["bx"], ControlMode(sp["kind"]))
    fb = data["feedback"]
    unit.feedback = None if fb is None else Feedback(**fb)
    unit.inputs = data["inputs"]["value"]
    unit.words = {name: word["value"] for name, word in data["words"].items()}
    status = {}
    for packet, record in data["status"].items():
        kind = PACKETS.get(int(packet))
        if kind is not None:
            status[int(packet)] = kind(**record)
    unit.status = status
    _take(unit.stats, data["stats"])
    unit.verify = data.get("verify")  # absent from an older service
    unit.foreign = data.get("foreign")
    unit.identified = data.get("identified")


def _take(record: Stats | BusView, data: dict[str, Any]) -> None:
    """The fields the service sent (it may send more); the others keep their values."""
    for f in fields(record):
        if f.name in data:
            setattr(record, f.name, data[f.name])
