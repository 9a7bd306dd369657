"""What the supervisor knows of each unit: setpoints sent, feedback and status received."""

from __future__ import annotations

from dataclasses import dataclass, field

from abh3_supervisor.config.model import ControlMode, UnitConfig, VelocityModel
from abh3_supervisor.core.kinematics import ab_to_yx, yx_to_ab
from abh3_supervisor.core.verify import Verification
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.generation import Generation


@dataclass(frozen=True, slots=True)
class Feedback:
    """Velocity feedback in both models [min⁻¹]; ``control`` only in the 2023 protocol."""

    t: float
    vel_a: float
    vel_b: float
    vel_y: float
    vel_x: float
    control: int | None = None

    @classmethod
    def from_reply(cls, t: float, reply: frames.Dp0Reply, model: VelocityModel) -> Feedback:
        if isinstance(reply, frames.Dp0Reply2021):
            return cls(t, reply.vel_a, reply.vel_b, reply.vel_y, reply.vel_x)
        if model is VelocityModel.TRAVEL:
            a, b = yx_to_ab(reply.vel_ay, reply.vel_bx)
            return cls(t, a, b, reply.vel_ay, reply.vel_bx, reply.control)
        y, x = ab_to_yx(reply.vel_ay, reply.vel_bx)
        return cls(t, reply.vel_ay, reply.vel_bx, y, x, reply.control)


@dataclass(frozen=True, slots=True)
class Setpoint:
    """The AY/BX command in the unit's model: min⁻¹, or % when ``kind`` is current;
    ``owner``: the input source it came from (core/inputs.py), None for zero."""

    ay: float = 0.0
    bx: float = 0.0
    kind: ControlMode = ControlMode.VELOCITY
    owner: str | None = None


@dataclass
class UnitState:
    cfg: UnitConfig
    inputs: int
    setpoint: Setpoint = field(default_factory=Setpoint)
    feedback: Feedback | None = None
    status: dict[int, tuple[float, frames.Broadcast]] = field(default_factory=dict)
    online: bool | None = None
    words: dict[str, int] = field(default_factory=dict)  # error, alarm, control, io, inputs
    # the drive's CAN settings against the file (core/verify.py)
    verify: Verification = field(init=False)
    # motor A, B speed limits [min⁻¹] that follow from the unit's robot's limits
    # (core/robot.py RobotConfig.axis_limit); None: its robot sets none
    axis_limits: tuple[float, float] | None = None

    layout: flags.Layout = field(init=False)  # the unit's generation's flag words
    # what the robot decision (core/readiness.py) reads of the drive: the axes that drive a
    # wheel; the generation its replies show (None: not yet); when this supervisor last
    # changed those axes' SERVO/START; the control word the drive reported in the latest
    # answer to a frame sent since then (None: none yet), and when; a gap in the exchanges
    wheels: tuple[int, ...] = (0, 1)
    identified: Generation | None = None
    changed_at: float = -float("inf")
    reported: int | None = None
    reported_at: float = -float("inf")
    reported_error: bool = False
    gap: bool = False
    probe_since: float = -float("inf")  # frames sent since carry the identity probe

    def __post_init__(self) -> None:
        self.layout = flags.layout(self.cfg.protocol)
        self.verify = Verification.initial(self.cfg)

    @classmethod
    def initial(cls, cfg: UnitConfig) -> UnitState:
        kind = cfg.control
        inputs = flags.layout(cfg.protocol).idle(
            *cfg.data_select, torque=kind is ControlMode.CURRENT
        )
        return cls(cfg, inputs, Setpoint(kind=kind))

    @property
    def name(self) -> str:
        return self.cfg.name
