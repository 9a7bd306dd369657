"""Which ``interface:`` names python-can accepts, and a did-you-mean for the others.

python-can's own list (``can.interfaces.VALID_INTERFACES``: its built-ins and every
installed ``can.interface`` entry point, our ``wacousb`` among them) is the one
``can.Bus(...)`` refuses a name by, so a name it does not know is a mistake in the file,
found by ``abh3 check`` as well as by ``run`` — also on a simulated bus, whose file is
meant for the robot too.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import can.util

from abh3_supervisor.errors import did_you_mean


def known_interfaces() -> frozenset[str]:
    # the set can.interfaces builds, as can.util holds it: can.Bus checks names there
    # (a test that registers an interface of its own patches it there too)
    return frozenset(can.util.VALID_INTERFACES)  # type: ignore[attr-defined]


def unknown_interface(name: str) -> str | None:
    """None when python-can knows ``name``; else what is wrong, with a did-you-mean."""
    known = known_interfaces()
    if name in known:
        return None
    # python-can's names are lower case, and it compares them exactly ("SocketCAN" fails)
    did = did_you_mean(name.lower(), sorted(known))
    return f"python-can has no interface '{name}'{did} (its interfaces: {', '.join(sorted(known))})"


# python-can interfaces that several processes share with no hardware at all: a
# `simulate:` bus on one has its drives in `abh3 simulate` by default (docs/simulator.md)
SHARED_BY_PROCESSES = frozenset({"udp_multicast"})
# interfaces that hand a process its own sent frames back: every member of a multicast
# group receives a datagram, its sender too, and python-can cannot turn that off
ECHOING = frozenset({"udp_multicast"})


def echoes_own_frames(interface: str, options: Mapping[str, Any]) -> bool:
    """Whether a bus opened so returns the frames its own process sent."""
    return interface in ECHOING or bool(options.get("receive_own_messages"))


def shared_bus(interface: str, channel: str) -> bool:
    """A bus other processes can share and no real drive can be on: where `abh3 simulate`
    may put its drives (a multicast group, or a SocketCAN virtual ``vcan`` device)."""
    return interface in SHARED_BY_PROCESSES or (
        interface == "socketcan" and re.fullmatch(r"vcan\d+", channel) is not None
    )
