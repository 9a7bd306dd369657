"""Another host on our drives, from the frames alone (docs/safety.md, "A second host").

Sans-I/O: fed the frames a bus delivers (never our own: no interface hands a process the
frames it sent) and the time, it says which other host touches which of our drives, with
what. A drive is *ours* when a unit commands it (``role: command``) on that bus.

Evidence, by how it is acted on:

- **commanding** (the supervisor stops the drive's robot and keeps it stopped):
  a DP0 command (PF 0xEF) to one of our drives — we never hear our own, so any such
  frame is another host's, whatever its source address (our own ``host_id`` included:
  the usual case is a second copy of us); a parameter session (J1939 transport, PF
  0xEC/0xEB) to one of our drives — we never hear the frames of the sessions we open,
  and a session may write any setting of the drive.
- **reading** (reported, never stops anything): a request (PF 0xEA) to one of our drives
  or to all; a DP0 reply from our drive to our host that no exchange of ours asked for
  (the scheduler decides which replies are ours: see ``UnitSlot.unasked``). A drive set to
  reply periodically (0x4105 > 0) sends those too, and on one wire the command or request
  that made a drive answer another host is always heard itself, so a reply alone never
  stops a drive.

A host's record starts an *episode* when first heard, or again after :data:`QUIET_S`
without a frame of it: the caller reports (and stops) once per episode, not per frame.

Read from other threads too (a plugin's ``/diagnostics``, ``SupervisorView.foreign_hosts``)
while the loop feeds it: the containers a reader iterates — :attr:`ForeignWatch.hosts` and
each record's :attr:`Foreign.heard` — are never changed once made, but replaced whole (one
atomic attribute assignment) when a host, an episode or a kind of frame is new, or a stop
is forgiven; a frame of a kind already heard only counts in place. So a reader iterates the
dict it took and never sees one change size under it, and the loop copies nothing per
frame. The numbers of a record (its count, its last time) may be one frame apart.
"""

from __future__ import annotations

import math
from collections.abc import Container, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from abh3_supervisor.protocol.ids import ADDR_ALL, PF_REQUEST, PF_SINGLE, PF_TP_CM, PF_TP_DT

# the foreign host must have been silent this long before a stop it caused may be cleared,
# and before its next frame is a new episode (reported again)
QUIET_S = 1.0
# a command or request a drive answers arrives within ~1 ms; a listener that must hear
# every host keeping a drive under command listens for the drive's command-zero timeout
# (0x4117, ``drive_timeout_ms``: a host silent that long has lost the drive) plus this
LISTEN_MARGIN_S = 0.1


class Evidence(StrEnum):
    COMMAND = "DP0 command"
    SESSION = "parameter session (TP)"
    REQUEST = "request"
    UNASKED_REPLY = "DP0 reply we did not ask for"


COMMANDING = frozenset({Evidence.COMMAND, Evidence.SESSION})


def evidence(arbitration_id: int, drives: Container[int]) -> tuple[Evidence, int, int] | None:
    """``(kind, drive, source)`` if a frame we received is another host's to one of
    ``drives`` (``drive`` is :data:`ADDR_ALL` for a request to all); None otherwise. A
    frame addressed to one of our drives is a host's whatever its source: drives never
    address each other, and no host of ours has a drive's address (the file's check), so
    a source that is one of our drives' addresses is another host using it."""
    pf, ps, sa = arbitration_id >> 16 & 0xFF, arbitration_id >> 8 & 0xFF, arbitration_id & 0xFF
    if arbitration_id >> 24 & 1:  # data page 1: no ABH3 frame (the drive ignores it too)
        return None
    if ps not in drives and not (pf == PF_REQUEST and ps == ADDR_ALL):
        return None
    if pf == PF_SINGLE:
        return Evidence.COMMAND, ps, sa
    if pf in (PF_TP_CM, PF_TP_DT):
        return Evidence.SESSION, ps, sa
    if pf == PF_REQUEST:
        return Evidence.REQUEST, ps, sa
    return None


@dataclass
class Heard:
    """The frames of one kind a foreign host sent (or caused) to one drive."""

    kind: Evidence
    arbitration_id: int  # the last one's
    data: bytes
    count: int
    first: float
    last: float

    def text(self) -> str:
        return f"{self.count} × {self.kind} (last {self.arbitration_id:08X} [{self.data.hex(' ')}])"

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind.value,
            "id": f"{self.arbitration_id:08X}",
            "data": self.data.hex(" "),
            "count": self.count,
            "first": self.first,
            "last": self.last,
        }


@dataclass
class Foreign:
    """One other host (source address) on one of our drives: every kind of frame heard."""

    source: int
    drive: int
    unit: str
    # replaced, never changed, once the record is in ForeignWatch.hosts (see the module)
    heard: dict[Evidence, Heard] = field(default_factory=dict)
    episode: float = 0.0  # when the present episode began
    last: float = -math.inf
    last_commanding: float = -math.inf

    @property
    def commanding(self) -> bool:
        return any(kind in COMMANDING for kind in self.heard)

    def who(self) -> str:
        if self.commanding or Evidence.REQUEST in self.heard:
            verb = "commands" if self.commanding else "reads"
            return f"another host (0x{self.source:02X}) {verb} drive 0x{self.drive:02X}"
        return (  # replies alone: they name no sender
            f"drive 0x{self.drive:02X} answers 0x{self.source:02X} unasked (another host "
            "asking in our name, or the drive's periodic DP0 replies: 0x4105)"
        )

    def text(self) -> str:
        """``another host (0x02) commands drive 0x01 (unit left): 12 × DP0 command (…)``."""
        frames = "; ".join(h.text() for h in self.heard.values())
        return f"{self.who()} (unit {self.unit}): {frames}"

    def to_json(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "drive": self.drive,
            "unit": self.unit,
            "commanding": self.commanding,
            "text": self.text(),
            "first": self.episode,
            "last": self.last,
            "frames": [h.to_json() for h in self.heard.values()],
        }


class ForeignWatch:
    """Every other host heard on our drives of one bus (see the module docstring)."""

    def __init__(self, drives: Mapping[int, str], quiet_s: float = QUIET_S) -> None:
        self.drives = dict(drives)  # address → unit name
        self.quiet_s = quiet_s
        # (source, drive) → record; replaced, never changed (see the module): iterate the
        # one taken, from any thread
        self.hosts: Mapping[tuple[int, int], Foreign] = {}

    def frame(self, arbitration_id: int, data: bytes, now: float) -> list[Foreign]:
        """A received frame that no exchange of ours routes: the records whose episode it
        begins (report and act on those), empty if it begins none or is not foreign."""
        found = evidence(arbitration_id, self.drives)
        if found is None:
            return []
        kind, drive, source = found
        targets = self.drives if drive == ADDR_ALL else (drive,)
        began = [self._heard(kind, d, source, arbitration_id, data, now) for d in targets]
        return [r for r in began if r is not None]

    def unasked_reply(
        self, drive: int, host: int, arbitration_id: int, data: bytes, now: float
    ) -> Foreign | None:
        """A DP0 reply of ``drive`` to ``host`` (our address) that no exchange of ours
        asked for: the record whose episode it begins, else None."""
        if drive not in self.drives:
            return None
        return self._heard(Evidence.UNASKED_REPLY, drive, host, arbitration_id, data, now)

    def _heard(
        self, kind: Evidence, drive: int, source: int, arbitration_id: int, data: bytes, now: float
    ) -> Foreign | None:
        key = source, drive
        record = self.hosts.get(key)
        if record is None or now - record.last > self.quiet_s:  # a new episode
            record = Foreign(source, drive, self.drives[drive], episode=now, last=now)
            record.heard = {kind: Heard(kind, arbitration_id, data, 1, now, now)}
            if kind in COMMANDING:
                record.last_commanding = now
            self.hosts = {**self.hosts, key: record}  # published whole, once made
            return record
        was_commanding = record.commanding
        heard = record.heard.get(kind)
        if heard is None:  # a kind not heard this episode: a new dict, never the old one
            record.heard = {**record.heard, kind: Heard(kind, arbitration_id, data, 1, now, now)}
        else:
            heard.arbitration_id, heard.data, heard.last = arbitration_id, data, now
            heard.count += 1
        record.last = now
        if kind in COMMANDING:
            record.last_commanding = now
        # a reader that starts commanding is news too: it now stops the drive
        if record.commanding and not was_commanding:
            return record
        return None

    def of(self, unit: str) -> list[Foreign]:
        """The records of ``unit``'s drive, commanding first."""
        found = [r for r in self.hosts.values() if r.unit == unit]
        return sorted(found, key=lambda r: (not r.commanding, r.source))

    def forgive(self, unit: str) -> None:
        """The stop ``unit``'s hosts caused was cleared: the next command of any of them is
        news again (a new stop), even within the episode — a host that kept reading the
        drive meanwhile, or a frame the bus had not yet been read for when it was cleared
        (the pump reads in batches: scheduler/pump.py). What it read stays on record."""
        for record in self.of(unit):
            kept = {kind: h for kind, h in record.heard.items() if kind not in COMMANDING}
            if len(kept) != len(record.heard):
                record.heard = kept  # a new dict: a reader goes on over the one it took

    def commanding(self, unit: str, now: float) -> list[Foreign]:
        """The hosts that commanded ``unit``'s drive within :attr:`quiet_s` of ``now``."""
        return [r for r in self.of(unit) if now - r.last_commanding <= self.quiet_s]


__all__ = [
    "COMMANDING",
    "LISTEN_MARGIN_S",
    "QUIET_S",
    "Evidence",
    "Foreign",
    "ForeignWatch",
    "Heard",
    "evidence",
]
