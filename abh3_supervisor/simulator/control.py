"""What ``abh3 simulate`` can be told while it runs, one line at a time.

    power off UNIT|all        the drive's power cut: silent, servo off, motors run down
    power on UNIT|all [keep]  power back: it boots (1 s), then answers as just switched on;
                              its parameters reloaded as set up (``keep``: with what was
                              written over CAN — no public source says which an ABH3 does)
    unplug UNIT|all           its CAN cable pulled: it hears and says nothing, and runs on
                              until its own command-zero timeout stops it
    plug UNIT|all             the cable back
    status                    each drive's state, one JSON object per line
    help

Each command is answered with one line (``ok …`` or ``error: …``; ``status`` and ``help``
then their lines); an empty line is no command and gets no answer.
Sans-I/O: :func:`obey` is given the time and returns the answer.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from abh3_supervisor.simulator.drive import SimDrive
from abh3_supervisor.simulator.watch import state

HELP = __doc__.split("\n\n")[1].rstrip() if __doc__ else ""


@dataclass
class Answer:
    text: str  # the line answered
    events: list[dict[str, Any]] = field(default_factory=list)  # for the trace
    quit: bool = False


def obey(line: str, drives: Mapping[str, SimDrive], now: float) -> Answer:
    words = line.split()
    if not words:
        return Answer("")
    verb, args = words[0].lower(), words[1:]
    if verb == "help":
        return Answer("ok\n" + HELP)
    if verb == "quit":
        return Answer("ok quit", quit=True)
    if verb == "status" and not args:
        lines = [json.dumps({"unit": name, **state(d)}) for name, d in drives.items()]
        return Answer("ok status\n" + "\n".join(lines))
    if verb == "power" and len(args) >= 2 and args[0] in ("on", "off"):
        keep = args[2:] == ["keep"] and args[0] == "on"
        if args[2:] and not keep:
            form = "power on UNIT|all [keep]" if args[0] == "on" else "power off UNIT|all"
            return Answer(f"error: {form}, not {_shown(line)}")
        return _each(drives, args[1], f"power_{args[0]}", now, keep=keep)
    if verb in ("unplug", "plug") and len(args) == 1:
        return _each(drives, args[0], f"{verb}ged", now)
    return Answer(f"error: unknown command {_shown(line)}; try help")


def _shown(line: str) -> str:
    """The line as said back: quoted, and cut short (a garbage line may be long)."""
    text = line.strip()
    return repr(text if len(text) <= 60 else text[:60] + "…")


def _each(
    drives: Mapping[str, SimDrive], who: str, action: str, now: float, *, keep: bool = False
) -> Answer:
    if who == "all":
        names = list(drives)
    elif who in drives:
        names = [who]
    else:
        return Answer(f"error: no simulated unit {who!r} (units: {', '.join(drives)})")
    events = []
    for name in names:
        drive = drives[name]
        if action == "power_off":
            drive.power_off(now)
        elif action == "power_on":
            drive.power_on(now, keep_writes=keep)
        else:
            drive.advance(now)
            drive.plugged = action == "plugged"
        events.append({"t": now, "unit": name, "event": action})
    return Answer(f"ok {action.replace('_', ' ')} {' '.join(names)}", events)
