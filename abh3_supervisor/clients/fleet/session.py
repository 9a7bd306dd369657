"""What ``abh3 fleet`` does with the broker, without a screen: what arrived into the
model, the broker's acknowledgements and the robots' word into the commands, and the
commands sent. The app (app.py) ticks it and paints; a test can drive it alone."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

from abh3_supervisor.clients.fleet.broker import Received
from abh3_supervisor.clients.fleet.commands import Commander, Sent
from abh3_supervisor.clients.fleet.model import FleetModel


class Link(Protocol):
    """The broker as the view uses it: the paho client (broker.py), a fake in tests."""

    connected: bool

    def drain(self) -> list[Received]: ...
    def take_acks(self) -> list[tuple[int, int, str]]: ...
    def publish(self, topic: str, payload: bytes) -> tuple[int, str | None]: ...
    def describe(self, now: float) -> str: ...


class Session:
    def __init__(
        self,
        model: FleetModel,
        commander: Commander,
        link: Link,
        reason: str,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.model, self.commander, self.link = model, commander, link
        self.reason, self.clock = reason, clock
        self.pending: dict[int, Sent] = {}  # mid: the command awaiting its PUBACK

    def tick(self) -> None:
        """Everything the link holds: messages into the model, then what is known of each
        command."""
        for message in self.link.drain():
            self.model.feed(message.topic, message.payload, message.retained, message.time)
        for mid, code, name in self.link.take_acks():
            sent = self.pending.pop(mid, None)
            if sent is not None:
                self.commander.acknowledged(sent, code, name)
        self.commander.observe(self.model)

    def send(self, target: str | None, *, clear: bool) -> Sent:
        """The e-stop (or its clear, ``clear``) to ``target`` (a fleet_id; None: all)."""
        sent = self.commander.build(
            self.model, target, clear=clear, reason=self.reason, now=self.clock()
        )
        mid, trouble = self.link.publish(sent.topic, sent.payload)
        self.pending[mid] = sent
        if trouble:
            sent.broker = trouble
        return sent
