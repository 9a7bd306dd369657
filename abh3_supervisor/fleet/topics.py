"""Every topic of the contract, from the prefix, a robot's ``fleet_id`` and the VDA 5050
manufacturer."""

from __future__ import annotations

from dataclasses import dataclass

PREFIX = "abh3/v1"
MANUFACTURER = "waco-giken-abh3"
VDA_PREFIX = "uagv/v2"
VDA_VERSION = "2.1.0"  # the VDA 5050 release whose schemas our messages follow
ALL = "all"  # the fleet_id level addressing every robot (commands only)
COMMANDS = ("estop", "estop_clear", "twist")


@dataclass(frozen=True)
class Topics:
    """One robot's topics."""

    fleet_id: str
    prefix: str = PREFIX
    manufacturer: str = MANUFACTURER

    @property
    def base(self) -> str:
        return f"{self.prefix}/{self.fleet_id}"

    @property
    def status(self) -> str:
        return f"{self.base}/status"

    def state(self, unit: str) -> str:
        return f"{self.base}/units/{unit}/state"

    @property
    def events(self) -> str:
        return f"{self.base}/events"

    @property
    def health(self) -> str:
        return f"{self.base}/health"

    def command(self, kind: str, *, everyone: bool = False) -> str:
        """``cmd/estop``, ``cmd/estop_clear`` or ``cmd/twist`` of this robot, or (``everyone``)
        of every robot (``{prefix}/all/cmd/…``; not for twist)."""
        if kind not in COMMANDS:
            raise ValueError(f"no command {kind!r} (commands: {', '.join(COMMANDS)})")
        return f"{self.prefix}/{ALL if everyone else self.fleet_id}/cmd/{kind}"

    @property
    def vda_base(self) -> str:
        return f"{VDA_PREFIX}/{self.manufacturer}/{self.fleet_id}"

    @property
    def connection(self) -> str:
        return f"{self.vda_base}/connection"

    @property
    def instant_actions(self) -> str:
        return f"{self.vda_base}/instantActions"


def command_kind(topic: str, prefix: str = PREFIX) -> tuple[str, str] | None:
    """``(fleet_id or 'all', kind)`` of a command topic under ``prefix``; None: not one."""
    head = f"{prefix}/"
    if not topic.startswith(head):
        return None
    parts = topic[len(head) :].split("/")
    if len(parts) != 3 or parts[1] != "cmd" or parts[2] not in COMMANDS:
        return None
    return parts[0], parts[2]


def robot_of(topic: str, prefix: str = PREFIX) -> tuple[str, str] | None:
    """``(fleet_id, rest)`` of any topic under ``prefix`` (``rest``: ``status``,
    ``units/left/state``, …); None: not under it."""
    head = f"{prefix}/"
    if not topic.startswith(head) or topic.count("/") < prefix.count("/") + 2:
        return None
    fid, _, rest = topic[len(head) :].partition("/")
    return fid, rest


@dataclass(frozen=True)
class Where:
    """What a topic under the prefix is, as a reader sorts it: ``kind`` one of status,
    state (of ``unit``), events, health, command (to a robot or ``all``), unknown."""

    fleet_id: str
    kind: str
    unit: str | None = None


def where(topic: str, prefix: str = PREFIX) -> Where | None:
    """The inverse of :class:`Topics` for a reader (``abh3 fleet``); None: not under
    ``prefix``."""
    found = robot_of(topic, prefix)
    if found is None:
        return None
    fid, rest = found
    if not fid:
        return Where(fid, "unknown")
    if command_kind(topic, prefix) is not None:
        return Where(fid, "command")
    if rest in ("status", "events", "health"):
        return Where(fid, rest)
    parts = rest.split("/")
    if len(parts) == 3 and parts[0] == "units" and parts[2] == "state" and parts[1]:
        return Where(fid, "state", parts[1])
    return Where(fid, "unknown")
