"""What the simulated drives do, as events: the truth a recording of the wire cannot hold.

After its host dies a drive hears nothing and says nothing — the wire goes quiet while
its motors still turn until its own command-zero timeout (0x4117) stops them. ``abh3
simulate --trace`` writes these events, one JSON object per line, so that a rehearsal
(docs/simulator.md) can show the last command, the timeout and the stop:

- ``moving`` / ``standing``: a motor started to turn / both stand (|v| < ``STILL``);
- ``command_zero_timeout``: the drive's own timeout fired (``at``: the last command plus
  its 0x4117 — exact, not the sample's time) and it stopped its axes;
- ``commanded``: commands again after such a timeout, from ``host``;
- ``state``: every sample while a motor turns (velocities, servo and start per axis).

Sans-I/O: :meth:`Watch.sample` is given the time; the caller writes the events.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from abh3_supervisor.simulator.drive import SimDrive

STILL = 0.5  # min⁻¹: below this a motor stands


@dataclass
class _Seen:
    moving: bool = False
    timed_out: bool = False
    last_command: float | None = None


def state(drive: SimDrive) -> dict[str, Any]:
    """The drive as it is: what ``status`` prints and each ``state`` event holds."""
    lay = drive.layout
    word = drive.control_word()
    return {
        "velocity": [round(v, 1) for v in drive.vel],
        "servo": [bool(word & lay.servo.of(axis)) for axis in (0, 1)],
        "start": [bool(word & lay.start.of(axis)) for axis in (0, 1)],
        "powered": drive.powered,
        "plugged": drive.plugged,
        "command_zero_timeout_ms": drive.command_zero_ms,
        "host": drive.host if drive.last_command is not None else None,  # who commanded it
    }


class Watch:
    def __init__(self, drives: Mapping[str, SimDrive]) -> None:
        self.drives = dict(drives)  # unit name → its drive
        self._seen = {name: _Seen() for name in self.drives}

    def sample(self, now: float) -> Iterator[dict[str, Any]]:
        """Each drive advanced to ``now``; the events since the last sample."""
        for name, drive in self.drives.items():
            drive.advance(now)
            yield from self._events(name, drive, self._seen[name], now)

    def _events(
        self, name: str, drive: SimDrive, seen: _Seen, now: float
    ) -> Iterator[dict[str, Any]]:
        base = {"t": now, "unit": name}
        last = drive.last_command
        timed_out = drive.command_zero_fired()
        if timed_out and not seen.timed_out and last is not None:
            yield {
                **base,
                "event": "command_zero_timeout",
                "at": last + drive.command_zero_ms / 1000,
                "last_command": last,
                "timeout_ms": drive.command_zero_ms,
            }
        elif seen.timed_out and not timed_out and last is not None and last != seen.last_command:
            yield {**base, "event": "commanded", "host": drive.host}
        seen.timed_out, seen.last_command = timed_out, last
        moving = any(abs(v) >= STILL for v in drive.vel)
        if moving and not seen.moving:
            yield {**base, "event": "moving", "velocity": [round(v, 1) for v in drive.vel]}
        if moving:
            yield {**base, "event": "state", **state(drive)}
        if seen.moving and not moving:
            since = None if last is None else round((now - last) * 1000, 1)
            yield {**base, "event": "standing", "since_last_command_ms": since}
        seen.moving = moving
