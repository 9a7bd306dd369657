"""``[HOST:]PORT``, where a server of ours listens (``--foxglove``, ``foxglove:``): the
loopback address unless a host is written, so nothing is reachable from the network
unless asked for."""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass, field

LOOPBACK = "127.0.0.1"
MAX_PORT = 65535
# HOST:PORT, [IPv6]:PORT or PORT alone (the JSON schema's pattern too: no named groups);
# the host is resolved when the server binds
PATTERN = r"^(?:([^\s:\[\]]+|\[[0-9A-Fa-f:.%\w]+\]):)?([0-9]{1,5})$"  # ASCII digits only
_FORM = re.compile(PATTERN)
SAID = "[HOST:]PORT (e.g. 8765, 0.0.0.0:8765, [::1]:8765; port 0: any free one)"


@dataclass(frozen=True)
class Endpoint:
    host: str
    port: int
    # where it was given, for a message: the option, or the file's line and key
    where: str = field(default="--foxglove", compare=False)

    def __str__(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"

    @property
    def loopback(self) -> bool:
        """Only this machine can reach it: a loopback address, or ``localhost`` (a name
        that merely starts with ``127.`` is not one)."""
        try:
            return ipaddress.ip_address(self.host.partition("%")[0]).is_loopback
        except ValueError:
            return self.host == "localhost"


def parse_endpoint(value: object) -> Endpoint:
    """``8765``, ``"0.0.0.0:8765"``, ``"[::1]:8765"``; ValueError saying what is wrong."""
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError(f"expected {SAID}, got {value!r}")
    match = _FORM.match(str(value).strip())
    if match is None:
        raise ValueError(f"'{value}' is not {SAID}")
    host, port = match[1] or LOOPBACK, int(match[2])
    if port > MAX_PORT:
        raise ValueError(f"port {port} is out of range (allowed 0–{MAX_PORT})")
    return Endpoint(host.removeprefix("[").removesuffix("]"), port)
