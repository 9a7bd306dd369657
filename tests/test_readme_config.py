"""The README's "Configuration in one screen" works as written: as a file for real drives
(interface: socketcan) it validates, and with its `simulate: true` line uncommented it runs
on the simulator — no can0 needed."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime

README = Path(__file__).resolve().parent.parent / "README.md"


def readme_yaml() -> str:
    section = README.read_text().split("## Configuration in one screen", 1)[1]
    match = re.search(r"```yaml\n(.*?)```", section, re.S)
    assert match, "the README's configuration example is gone"
    return match.group(1)


def test_the_readme_example_validates_as_written() -> None:
    config = parse_config(readme_yaml(), "README.md")
    bus = config.buses["can0"]
    assert (bus.interface, bus.channel, bus.simulate) == ("socketcan", "can0", None)


@pytest.mark.wallclock
def test_the_readme_example_runs_on_the_simulator_with_simulate_uncommented() -> None:
    text = readme_yaml().replace("# simulate: true", "simulate: true")
    assert "    simulate: true" in text
    config = parse_config(text, "README.md")
    assert config.buses["can0"].interface == "socketcan"

    async def scenario() -> Runtime:
        async with Runtime(config) as rt:
            sup = rt.supervisor
            assert await sup.wait_exchange("base", sup.clock(), 3.0)
            # the startup commands reached the simulated drive: it reports SERVO on
            for _ in range(100):
                if sup.unit("base").words.get("control", 0) & sup.unit("base").layout.servo.both:
                    break
                assert await sup.wait_exchange("base", sup.clock(), 1.0)
            else:
                raise AssertionError("the drive never reported SERVO on")
        return rt

    rt = asyncio.run(scenario())
    assert rt.stops_confirmed
