"""YAML configuration: load, validate with file:line:key messages, typed model."""

from abh3_supervisor.config.model import (
    BroadcastConfig,
    BusConfig,
    Config,
    ControlMode,
    Limits,
    Role,
    SimConfig,
    UnitConfig,
    VelocityModel,
)
from abh3_supervisor.config.parse import load_config, parse_config

__all__ = [
    "BroadcastConfig",
    "BusConfig",
    "Config",
    "ControlMode",
    "Limits",
    "Role",
    "SimConfig",
    "UnitConfig",
    "VelocityModel",
    "load_config",
    "parse_config",
]
