"""Real-time buses: simulated drives on a channel of their own, and a bus's notices."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterator

import can

from abh3_supervisor.config import Config
from abh3_supervisor.config.model import SimConfig
from abh3_supervisor.core.supervisor import Notice, SupervisorEvent
from abh3_supervisor.scheduler.pump import BusPump
from abh3_supervisor.simulator import SimBus


class BusNotices:
    """An observer keeping one bus's notices (``bus NAME: …``), awaited one at a time."""

    def __init__(self, bus: str) -> None:
        self.prefix = f"bus {bus}:"
        self.seen: list[str] = []
        self._changed = asyncio.Event()

    def __call__(self, event: SupervisorEvent) -> None:
        if isinstance(event, Notice) and event.message.startswith(self.prefix):
            self.seen.append(event.message)
            self._changed.set()

    async def next(self) -> str:
        await asyncio.wait_for(self._changed.wait(), 3.0)
        self._changed.clear()
        return self.seen[-1]


@contextlib.contextmanager
def drives_on(config: Config, bus: str, channel: str) -> Iterator[BusPump]:
    """The simulated drives of ``bus`` on a virtual channel of their own, pumped on the
    running loop: the far side of an interface the supervisor opens (a fake, an adapter)."""
    sim = SimBus.for_units(config.units_on(bus), SimConfig(), asyncio.get_running_loop().time())
    sim_bus = can.Bus(interface="virtual", channel=channel)
    pump = BusPump(sim_bus, sim, name=f"{bus} drives", channel=channel)
    pump.start()
    try:
        yield pump
    finally:
        pump.stop()
        sim_bus.shutdown()
