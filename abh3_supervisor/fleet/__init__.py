"""The fleet contract (docs/fleet.md): topic names, identities, payloads and their JSON
Schemas, as small pure functions both sides use — the ``mqtt`` plugin that publishes and
obeys, and ``abh3 fleet`` that reads and commands. No network here (no MQTT client
import): what goes over the wire is built and checked here, sent elsewhere.
"""

from abh3_supervisor.fleet import ids, payloads, schemas, topics
from abh3_supervisor.fleet.ids import (
    client_id,
    commands_client_id,
    default_name,
    fleet_id,
    safe,
    stop_client_id,
    vda_client_id,
)
from abh3_supervisor.fleet.payloads import Command, Refused, SeqGuard, Sequence, UnitReport
from abh3_supervisor.fleet.topics import (
    ALL,
    COMMANDS,
    MANUFACTURER,
    PREFIX,
    Topics,
    Where,
    command_kind,
    robot_of,
    where,
)

__all__ = [
    "ALL",
    "COMMANDS",
    "MANUFACTURER",
    "PREFIX",
    "Command",
    "Refused",
    "SeqGuard",
    "Sequence",
    "Topics",
    "UnitReport",
    "Where",
    "client_id",
    "command_kind",
    "commands_client_id",
    "default_name",
    "fleet_id",
    "ids",
    "payloads",
    "robot_of",
    "safe",
    "schemas",
    "stop_client_id",
    "topics",
    "vda_client_id",
    "where",
]
