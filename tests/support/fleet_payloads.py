"""Hand-made payloads of the fleet contract (docs/fleet.md), as the mqtt plugin publishes
them: for the model's, the view's and the end-to-end tests of ``abh3 fleet``."""

from __future__ import annotations

import json
from typing import Any

PREFIX = "abh3/v1"
T0 = 1_800_000_000.0  # a wall-clock time for the fake clocks


def status_topic(fid: str) -> str:
    return f"{PREFIX}/{fid}/status"


def state_topic(fid: str, unit: str) -> str:
    return f"{PREFIX}/{fid}/units/{unit}/state"


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
    body: dict[str, Any] = {
        "v": 1,
        "time": time,
        "seq": seq,
        "fleet_id": fid,
        "robot": fid.split("-")[-1],
        "state": state,
        "host": "agv-host",
        "pid": 4242,
        "version": "0.9.0",
        "units": list(units),
        "attach": attach,
    }
    return json.dumps(body | extra).encode()


def unit_state(fid: str, unit: str, *, time: float = T0, seq: int = 1, **fields: Any) -> bytes:
    body: dict[str, Any] = {
        "v": 1,
        "time": time,
        "seq": seq,
        "fleet_id": fid,
        "robot": fid.split("-")[-1],
        "unit": unit,
        "online": True,
        "servo": [True, True],
        "start": [True, False],
        "commanded": {"ay": 300.0, "bx": 0.0},
        "measured": {"a": 298.5, "b": None},
        "errors": [],
        "alarms": [],
        "owner": "tui:operator",
        "estop": False,
        "verify": "ok",
        "foreign_host": None,
        "age_s": 0.02,
    }
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
    body = {
        "v": 1,
        "time": time,
        "seq": seq,
        "fleet_id": fid,
        "robot": fid.split("-")[-1],
        "unit": None,
        "kind": kind,
        "text": text,
        "data": data or {},
    }
    return json.dumps(body).encode()
