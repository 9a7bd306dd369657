"""The ROS 2 plugin on the fake clock: an in-memory transport, the supervisor and the
simulated drives of tests/support/rig.py, the plugin's sources in the arbitration and its
hooks fed as the plugin host feeds them (tests/test_nav_*.py, tests/test_ros2_robot.py)."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from abh3_plugins.ros2 import bridge as bridge_module
from abh3_plugins.ros2.bridge import Ros2Plugin
from abh3_plugins.ros2.settings import Settings, parse
from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.config.source import Section
from abh3_supervisor.core.commands import VelocityCommand
from abh3_supervisor.core.inputs import InputSource, Twist
from abh3_supervisor.core.robot import RobotConfig
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.plugin_host.view import SupervisorView
from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.core import FeedbackEvent, StatusEvent
from tests.support.rig import Rig
from tests.support.ros2_memory import MemoryTransport


class SyncFeed:
    """An input source's feed on the fake clock: straight into the arbitration."""

    def __init__(self, sup: Supervisor, source: InputSource) -> None:
        self.sup, self.source = sup, source

    def twist(self, linear_x: float, angular_z: float) -> None:
        self.sup.arbiter.submit(self.source.name, Twist(linear_x, angular_z), self.sup.clock())

    def velocity(self, ay: float, bx: float) -> None:
        self.sup.arbiter.submit(self.source.name, VelocityCommand(ay, bx), self.sup.clock())


class Bridged:
    """A rig with the ROS 2 plugin configured by the file's own ``plugins.ros2`` (or by
    ``settings``): its sources in the arbitration, its hooks fed."""

    def __init__(
        self,
        text: str,
        monkeypatch: pytest.MonkeyPatch,
        enable: bool = True,
        settings: Settings | None = None,
    ) -> None:
        self.config: Config = parse_config(text, "robot.yaml")
        self.rig = Rig(self.config)
        sup = self.rig.sup
        if enable:
            for unit in self.config.units:
                for command in ("SERVO ON ON", "START ON ON"):
                    sup.apply_text(unit, command)
        self.t = MemoryTransport()
        monkeypatch.setattr(bridge_module, "open_transport", lambda settings: self.t)
        self.plugin = Ros2Plugin()
        assert self.config.source is not None
        if settings is None:
            raw = self.config.plugins.get("ros2") or {}
            section = Section(self.config.source, ("plugins", "ros2"), raw, None)
            settings = parse(section, self.config)
            self.config.source.raise_if_problems()
        self.plugin.settings = settings
        loop = asyncio.new_event_loop()  # no loop on the fake clock
        loop.close()
        self.plugin.abh3_start(SupervisorView(sup, loop, "ros2"))
        self.sources: dict[str, InputSource] = {}
        self.plugin.abh3_input_sources(self._register)
        sup.subscribe(self._observe)

    def _register(self, source: InputSource) -> None:
        self.sources[source.name] = source
        self.rig.sup.arbiter.add(source)
        source.start(SyncFeed(self.rig.sup, source))

    def _observe(self, event: object) -> None:
        """The plugin host's translation of events into hooks (host.py), on this thread."""
        sup = self.rig.sup
        if isinstance(event, StatusEvent) and not isinstance(event.record, frames.Unknown):
            self.plugin.abh3_status(event.unit, event.packet, event.record, event.t)
        elif isinstance(event, FeedbackEvent):
            feedback = sup.units[event.unit].feedback
            if feedback is not None:
                self.plugin.abh3_feedback(event.unit, feedback)

    def robot(self) -> RobotConfig:
        return next(r for r in self.config.robots.values() if not r.implicit)

    def motor(self, unit: str, axis: int) -> float:
        return float(self.rig.drive(unit).vel[axis])

    def published(self, name: str) -> list[Any]:
        return self.t.published.setdefault(name, [])
