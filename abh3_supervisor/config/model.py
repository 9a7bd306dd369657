"""The typed configuration every other module reads. Defaults are the seed's."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from abh3_supervisor.config.endpoint import Endpoint
from abh3_supervisor.config.source import Source
from abh3_supervisor.core.kinematics import Geometry
from abh3_supervisor.core.robot import RobotConfig, from_geometry
from abh3_supervisor.params.telabh3 import TelFormat
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.protocol.scaling import CURRENT, VELOCITY


class ControlMode(StrEnum):
    VELOCITY = "velocity"
    CURRENT = "current"


class VelocityModel(StrEnum):
    """How the drive is parameterised: what its AY/BX command fields mean."""

    TRAVEL = "travel"  # Y = travel, X = turn (the vendor sample's launch files)
    MOTOR = "motor"  # A, B = the two motors


class Role(StrEnum):
    COMMAND = "command"  # we send DP0 commands (and so keep the drive's timeout fed)
    MONITOR = "monitor"  # we only ask for DP0 replies (request PGN): never moves a motor


class VerifyMode(StrEnum):
    """What a mismatch between the drive's CAN settings and the file does (core/verify.py)."""

    WARN = "warn"  # logged and shown; the unit runs
    REFUSE = "refuse"  # the unit stays at its idle word: no SERVO, no START
    OFF = "off"  # not read at start


class FaultKind(StrEnum):
    SILENT = "silent"  # the drive hears, never answers
    MALFORMED_REPLIES = "malformed_replies"  # its replies carry no data bytes (DLC 0)
    ERROR_BITS = "error_bits"  # error bits present (servo off) while the fault lasts
    BUS_SEND_ERROR = "bus_send_error"  # the bus refuses the supervisor's frames
    SLOW_REPLIES = "slow_replies"  # replies come ``delay_ms`` late
    # the parameter transport (J1939 TP, simulator/telabh3.py)
    TP_LOST_CTS = "tp_lost_cts"  # an RTS is heard and never answered
    TP_ABORT = "tp_abort"  # an RTS is answered with an abort (reason 2, resources)
    TP_SLOW_DT = "tp_slow_dt"  # the drive's DTs come ``delay_ms`` apart
    # wiring and set-up mistakes (permanent unless timed): what `abh3 commission` finds
    REVERSED_AXIS = "reversed_axis"  # the motor's feedback (velocity, pulses) has its sign inverted
    SWAPPED_AXES = "swapped_axes"  # A's command drives motor B and B's drives motor A
    SCALE = "scale"  # the motor's pulses count ``factor`` × what the file's geometry expects
    NO_ENCODER = "no_encoder"  # no feedback, no pulses; the current rises as when stalled
    OTHER_VELOCITY_MODEL = "other_velocity_model"  # the drive runs the model the file does not
    # how the robot is built (simulator/robot.py): per-motor checks pass, the robot's fail
    MIRRORED_WHEEL = "mirrored_wheel"  # the motor is mounted opposite to its wheel's sign
    SWAPPED_DRIVES = "swapped_drives"  # ``unit`` and ``other`` sit on each other's wheels
    SWAPPED_AXES_WITH_ENCODERS = "swapped_axes_with_encoders"  # A and B, encoders and all
    WRONG_PROTOCOL = "wrong_protocol"  # the drive is of the other generation than the file's
    WRONG_TRACK = "wrong_track"  # the robot's true track is ``factor`` × the file's
    WRONG_DIAMETER = "wrong_diameter"  # the unit's wheels are ``factor`` × the file's diameter


# how the robot or the drive is built: the simulator builds them once, untimed
BUILT_KINDS = frozenset(
    {
        FaultKind.MIRRORED_WHEEL,
        FaultKind.SWAPPED_DRIVES,
        FaultKind.SWAPPED_AXES_WITH_ENCODERS,
        FaultKind.WRONG_PROTOCOL,
        FaultKind.WRONG_TRACK,
        FaultKind.WRONG_DIAMETER,
    }
)
# kinds that describe how a drive is wired or set up: from the start, for ever, by default
WIRING_KINDS = BUILT_KINDS | {
    FaultKind.REVERSED_AXIS,
    FaultKind.SWAPPED_AXES,
    FaultKind.SCALE,
    FaultKind.NO_ENCODER,
    FaultKind.OTHER_VELOCITY_MODEL,
}
AXIS_KINDS = frozenset(
    {FaultKind.REVERSED_AXIS, FaultKind.SCALE, FaultKind.NO_ENCODER, FaultKind.MIRRORED_WHEEL}
)

STOP_RAMP_S = 1.0  # s: the default of `stop_ramp_s`


@dataclass(frozen=True)
class Fault:
    """A scripted fault of the simulator, from ``at_s`` after start for ``for_s``."""

    kind: FaultKind
    at_s: float
    for_s: float
    unit: str | None = None  # None: every simulated drive on the bus
    bits: int = 1 << 6  # error_bits: which error bits (default A overcurrent)
    delay_ms: float = 50.0  # slow_replies, tp_slow_dt
    axis: int = 0  # reversed_axis, scale, no_encoder: motor A (0) or B (1)
    factor: float = 1.0  # scale: pulses counted per expected pulse; wrong_track/_diameter
    other: str | None = None  # swapped_drives: the unit on whose wheels ``unit``'s drive sits

    def active(self, since_start: float) -> bool:
        return self.at_s <= since_start < self.at_s + self.for_s


@dataclass(frozen=True)
class SimConfig:
    """Built-in simulator options (see docs/configuration.md)."""

    # None: each simulated drive has its unit's drive_timeout_ms (what the file says the
    # drive is set to); a number sets every drive on the bus, e.g. to rehearse a mismatch
    command_zero_timeout_ms: int | None = None
    error_timeout_ms: int = 1000
    accel: float = 3000.0  # min⁻¹ per second, both directions
    # a first-order velocity response instead of the ramp at ``accel`` [ms]; None: the ramp
    time_constant_ms: float | None = None
    # per unit, a time constant of its own: ((unit, ms), ...)
    unit_time_constant_ms: tuple[tuple[str, float], ...] = ()
    reply_latency_ms: float = 0.2
    dp0_period_ms: int = 0  # > 0: the drive also sends DP0 replies periodically
    broadcast_period_ms: int = 0  # > 0: the drive also sends its broadcasts periodically
    faults: tuple[Fault, ...] = ()  # scripted faults, to rehearse them (and for tests)
    # per unit, parameter words that differ from what the file says (to rehearse a drive
    # set up differently): ((unit, ((address, word), ...)), ...)
    params: tuple[tuple[str, tuple[tuple[int, int], ...]], ...] = ()
    # per unit, the only TelABH3 forms its drive reads (() none); a unit not named reads all
    telabh3_forms: tuple[tuple[str, tuple[TelFormat, ...]], ...] = ()
    # per unit, commands run at start after its own ``startup:``, only while simulated (a
    # demo's motion: the same file on a real bus waits): ((unit, (command, ...)), ...)
    startup: tuple[tuple[str, tuple[str, ...]], ...] = ()
    # the drives run in `abh3 simulate` (a process of their own, on the bus's interface);
    # `run`, `commission`, `param` open the bus as a real one (docs/simulator.md)
    external: bool = False

    def params_of(self, unit: str) -> dict[int, int]:
        return dict(next((words for name, words in self.params if name == unit), ()))

    def time_constant_of(self, unit: str) -> float | None:
        """``unit``'s drive's velocity time constant [ms]; None: it ramps at ``accel``."""
        return dict(self.unit_time_constant_ms).get(unit, self.time_constant_ms)

    def forms_of(self, unit: str) -> tuple[TelFormat, ...] | None:
        """The forms ``unit``'s drive reads; None: every form."""
        return next((forms for name, forms in self.telabh3_forms if name == unit), None)


# units whose commands leave in one turn of the schedule (one wake-up of the host) unless
# the bus says otherwise: a burst this size, each unit's status poll beside its command,
# stays within a SocketCAN interface's default transmit queue (10 frames)
UNITS_PER_TURN = 4
MAX_UNITS_PER_TURN = 64


@dataclass(frozen=True)
class BusConfig:
    name: str
    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = 500_000
    simulate: SimConfig | None = None
    options: dict[str, Any] = field(default_factory=dict)
    units_per_turn: int = UNITS_PER_TURN


@dataclass(frozen=True)
class BroadcastConfig:
    mask: int = 0x7F
    rate_hz: float = 10.0  # packet requests per second, round-robin over the mask
    listen_only: bool = False  # the drive sends them periodically; never poll

    @property
    def packets(self) -> tuple[int, ...]:
        return tuple(n for n in range(7) if self.mask >> n & 1)


@dataclass(frozen=True)
class Limits:
    # min⁻¹ and % per axis, either sign; the default is the whole wire range (−6553.6 …
    # 6553.4 min⁻¹, −327.68 … 327.67 %): a limit never widens it
    velocity: float = VELOCITY.largest
    current: float = CURRENT.largest


@dataclass(frozen=True)
class UnitConfig:
    name: str
    bus: str
    abh3_id: int = 1
    host_id: int = 2
    priority: int = 0
    brd_group: int = 5
    protocol: Generation = Generation.G2021
    timeout_ms: int = 1000
    reply_timeout_ms: int = 100
    # the drive's own command-zero timeout, parameter 0x4117 (the seed's drive: 500 ms):
    # no command for this long and the drive stops itself
    drive_timeout_ms: int = 500
    command_rate_hz: float = 50.0
    control: ControlMode = ControlMode.VELOCITY
    velocity_model: VelocityModel = VelocityModel.TRAVEL
    role: Role = Role.COMMAND
    broadcast: BroadcastConfig = field(default_factory=BroadcastConfig)
    geometry: Geometry = field(default_factory=Geometry)
    limits: Limits = field(default_factory=Limits)
    data_select: tuple[int, int] = (7, 7)
    startup: tuple[str, ...] = ()
    # how TelABH3 strings are written on CAN: not settled by public sources
    # (docs/parameters.md); None (no `telabh3:`): found by the first exchange
    telabh3: TelFormat | None = None
    # whether the drive's CAN settings are read at start and compared with this file
    verify: VerifyMode = VerifyMode.WARN


@dataclass(frozen=True)
class Config:
    file: str
    buses: dict[str, BusConfig]
    units: dict[str, UnitConfig]
    plugins: dict[str, Any] = field(default_factory=dict)
    # line of each plugin section, so plugins can report file:line like the core
    plugin_lines: dict[str, int] = field(default_factory=dict)
    # the parsed document with positions, for validating plugin sections later
    source: Source | None = field(default=None, compare=False, repr=False)
    # the YAML as read: a client of the control socket rebuilds this same Config from it
    text: str = field(default="", compare=False, repr=False)
    # the robots the file declares (``robots:``); every commanded unit not a wheel of one
    # is a one-drive robot of its own, named after it, from its ``geometry`` (added here)
    declared_robots: dict[str, RobotConfig] = field(default_factory=dict)
    # `foxglove: [HOST:]PORT`: the recording's topics served live (runtime/foxglove_live.py)
    foxglove: Endpoint | None = None
    # `stop_ramp_s`: the normal way out waits at most this long for the drives to report
    # standing before SERVO and brake release go off (stop category 1)
    stop_ramp_s: float = STOP_RAMP_S
    # the declared robots whose units are all here, then the one-drive robots
    robots: dict[str, RobotConfig] = field(default_factory=dict, init=False, compare=False)
    _by_unit: dict[str, RobotConfig] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        for name, robot in self.declared_robots.items():
            if all(u in self.units for u in robot.units):
                self.robots[name] = robot
        wheels_of = {u for r in self.robots.values() for u in r.units}
        for unit in self.units.values():
            if unit.role is Role.COMMAND and unit.name not in wheels_of:
                self.robots.setdefault(unit.name, from_geometry(unit.name, unit.geometry))
        self._by_unit.update((u, r) for r in self.robots.values() for u in r.units)

    def units_on(self, bus: str) -> list[UnitConfig]:
        return [u for u in self.units.values() if u.bus == bus]

    def robot_of(self, unit: str) -> RobotConfig | None:
        """The robot ``unit`` is a wheel drive of; None for a monitor unit."""
        return self._by_unit.get(unit)

    def robot(self, name: str) -> RobotConfig | None:
        """The robot called ``name``, or the robot of the unit called ``name``."""
        return self.robots.get(name) or self.robot_of(name)
