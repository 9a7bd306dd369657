"""Which ``interface:`` names python-can accepts, and a did-you-mean for the others.

python-can's own list (``can.interfaces.VALID_INTERFACES``: its built-ins and every
installed ``can.interface`` entry point, our ``wacousb`` among them) is the one
``can.Bus(...)`` refuses a name by, so a name it does not know is a mistake in the file,
found by ``abh3 check`` as well as by ``run`` — also on a simulated bus, whose file is
meant for the robot too.
"""

from __future__ import annotations

import difflib

import can.util


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
    hint = difflib.get_close_matches(name.lower(), sorted(known), n=1)
    did = f"; did you mean '{hint[0]}'?" if hint else ""
    return f"python-can has no interface '{name}'{did} (its interfaces: {', '.join(sorted(known))})"
