"""Who a robot is on the broker: its ``fleet_id``, its MQTT client ids."""

from __future__ import annotations

import re
import socket

_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


def safe(text: str) -> str:
    """``text`` with every character outside ``[A-Za-z0-9_.-]`` made ``_``: a topic level
    and a client id of its own (no ``/``, ``+``, ``#``, spaces)."""
    return _UNSAFE.sub("_", text)


def default_name() -> str:
    """The plugin's ``name`` unless set: this machine's hostname, lower case."""
    return safe(socket.gethostname().lower()) or "abh3"


def fleet_id(name: str, robot: str) -> str:
    """``{name}-{robot}``, made safe: a topic level, the VDA 5050 ``serialNumber``."""
    return safe(f"{name}-{robot}")


def client_id(fid: str) -> str:
    """The MQTT client id of a robot's connection."""
    return f"abh3-{fid}"


def commands_client_id(fid: str) -> str:
    """The client id of a robot's commands connection (the fleet's twists only: its reading
    is held to a cap, and nothing we publish waits behind what it has not read)."""
    return f"abh3-{fid}.cmd"


def stop_client_id(fid: str) -> str:
    """The client id of a robot's stop connection (e-stop and clear only: never behind
    another command)."""
    return f"abh3-{fid}.stop"


def vda_client_id(fid: str) -> str:
    """The client id of a robot's VDA 5050 connection (its own last will: one MQTT
    connection carries only one)."""
    return f"abh3-{fid}.vda"
