"""The contract's JSON Schemas (draft 2020-12), one file per payload: ``load(name)``."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

NAMES = ("status", "unit_state", "event", "health", "estop_command", "twist_command")


def load(name: str) -> dict[str, Any]:
    """The schema of payload ``name`` (one of :data:`NAMES`)."""
    if name not in NAMES:
        raise KeyError(f"no schema {name!r} (schemas: {', '.join(NAMES)})")
    text = resources.files(__name__).joinpath(f"{name}.json").read_text("utf-8")
    schema: dict[str, Any] = json.loads(text)
    return schema
