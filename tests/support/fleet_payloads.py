"""Payloads of the fleet contract (docs/fleet.md) for the model's, the view's and the
end-to-end tests of ``abh3 fleet``: built by the very builders the mqtt plugin uses
(``abh3_supervisor.fleet.payloads``), then any field overridden — a test may break one
on purpose."""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from abh3_supervisor.fleet import PREFIX, Topics, payloads

__all__ = ["PREFIX", "T0", "event", "state_topic", "status", "status_topic", "unit_state"]

T0 = 1_800_000_000.0  # a wall-clock time for the fake clocks


def status_topic(fid: str) -> str:
    return Topics(fid).status


def state_topic(fid: str, unit: str) -> str:
    return Topics(fid).state(unit)


def _robot(fid: str) -> str:
    return fid.split("-")[-1]


def status(
    fid: str,
    state: str = "online",
    *,
    time: float = T0,
    seq: int = 1,
    units: tuple[str, ...] = ("left", "right"),
    attach: str | None = None,
    **extra: Any,
) -> bytes:
    body = payloads.status(
        seq,
        time,
        fleet_id=fid,
        robot=_robot(fid),
        state="online",  # then ``state`` as given: a test may give one the contract has not
        host="agv-host",
        pid=4242,
        version="0.9.0",
        units=list(units),
        attach=attach,
    )
    return json.dumps(body | {"state": state} | extra).encode()


REPORT = payloads.UnitReport(
    unit="-",
    online=True,
    servo=(True, True),
    start=(True, False),
    commanded=(300.0, 0.0),
    measured=(298.5, None),
    owner="tui:operator",
    verify="ok",
    age_s=0.02,
)


def unit_state(fid: str, unit: str, *, time: float = T0, seq: int = 1, **fields: Any) -> bytes:
    report = dataclasses.replace(REPORT, unit=unit)
    body = payloads.unit_state(seq, time, fleet_id=fid, robot=_robot(fid), report=report)
    return json.dumps(body | fields).encode()


def event(
    fid: str,
    kind: str,
    text: str,
    *,
    time: float = T0,
    seq: int = 1,
    data: dict[str, Any] | None = None,
) -> bytes:
    body = payloads.event(
        seq, time, fleet_id=fid, robot=_robot(fid), unit=None, kind=kind, text=text, data=data
    )
    return json.dumps(body).encode()
