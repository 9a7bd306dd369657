"""The ROS 2 bridge's transport in memory: what it publishes is kept, the test delivers
samples to its subscriptions and calls its services (no DDS, no ROS)."""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable
from typing import Any

from abh3_plugins.ros2 import types


class MemoryTransport:
    """Publishers append to lists; the test delivers samples to the subscriptions."""

    msg = types

    def __init__(self) -> None:
        self.published: dict[str, list[Any]] = {}
        self.handlers: dict[str, Callable[[Any], None]] = {}
        self.services: dict[str, Callable[[str], concurrent.futures.Future[str]]] = {}

    def publisher(self, name: str, typ: type) -> Callable[[Any], None]:
        return self.published.setdefault(name, []).append

    def subscribe(self, name: str, typ: type, handle: Callable[[Any], None]) -> None:
        self.handlers[name] = handle

    def serve(self, name: str, handle: Callable[[str], concurrent.futures.Future[str]]) -> None:
        self.services[name] = handle

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass
