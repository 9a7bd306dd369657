"""Shared fixtures: fake-clock setups and a guard against leaked virtual buses."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from can.interfaces import virtual

from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.simulator import SimBus
from abh3_supervisor.simulator.timeline import Timeline

TWO_UNITS = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50, broadcast: {mask: 0x7f, rate_hz: 14}}
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor, command_rate_hz: 50,
     broadcast: {mask: 0x0f, rate_hz: 8}}
"""


class Rig:
    """A supervisor and simulated drives on one fake-clock bus."""

    def __init__(self, config: Config, bitrate: int | None = None) -> None:
        self.timeline = Timeline(bitrate)
        self.config = config
        self.sup = Supervisor(config, clock=self.timeline.clock)
        bus = next(iter(config.buses))
        sim_cfg = config.buses[bus].simulate
        assert sim_cfg is not None
        self.sim = SimBus.for_units(config.units_on(bus), sim_cfg, 0.0)
        self.scheduler = self.sup.schedulers[bus]
        self.timeline.add(self.scheduler, after_step=lambda: self.sup.dispatch(bus))
        self.timeline.add(self.sim)
        self.events: list[object] = []
        self.sup.subscribe(self.events.append)

    def run(self, seconds: float) -> None:
        self.timeline.run_until(self.timeline.now + seconds)

    def drive(self, unit: str):  # type: ignore[no-untyped-def]
        return self.sim.drives[self.config.units[unit].abh3_id]


@pytest.fixture
def rig() -> Rig:
    return Rig(parse_config(TWO_UNITS, "two.yaml"))


@pytest.fixture(autouse=True)
def no_leaked_buses() -> Iterator[None]:
    yield
    leaked = {name: len(ch) for name, ch in virtual.channels.items() if ch}
    virtual.channels.clear()
    assert not leaked, f"virtual buses left open: {leaked}"


@pytest.fixture(autouse=True)
def private_runtime_dir() -> Iterator[None]:
    """Supervisors the tests start serve their sockets here, never in the user's own
    runtime directory (where `abh3 tui` and `abh3 status` would find them)."""
    saved = os.environ.get("XDG_RUNTIME_DIR")
    runtime = Path(tempfile.mkdtemp(dir="/tmp", prefix="abh3t-"))  # short: AF_UNIX paths
    os.environ["XDG_RUNTIME_DIR"] = str(runtime)
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop("XDG_RUNTIME_DIR", None)
        else:
            os.environ["XDG_RUNTIME_DIR"] = saved
        shutil.rmtree(runtime, ignore_errors=True)
