"""Several simulated drives sharing one bus, with the scheduler's machine shape."""

from __future__ import annotations

import math
from collections.abc import Iterable

from abh3_supervisor.config.model import SimConfig, UnitConfig
from abh3_supervisor.simulator.drive import SimDrive


class SimBus:
    """Feeds every frame to every drive and collects what they send, in time order."""

    def __init__(self, drives: Iterable[SimDrive]) -> None:
        self.drives = {d.abh3_id: d for d in drives}

    @classmethod
    def for_units(cls, units: Iterable[UnitConfig], cfg: SimConfig, now: float) -> SimBus:
        return cls(
            SimDrive(
                u.abh3_id,
                group=u.brd_group,
                generation=u.protocol,
                model=u.velocity_model,
                cfg=cfg,
                now=now,
            )
            for u in units
        )

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        for drive in self.drives.values():
            drive.on_frame(arbitration_id, data, now)

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        out: list[tuple[int, bytes]] = []
        for drive in self.drives.values():
            out.extend(drive.poll(now))
        return out

    def next_deadline(self) -> float:
        return min((d.next_deadline() for d in self.drives.values()), default=math.inf)

    def on_send_failed(self, arbitration_id: int) -> None:
        """A drive's reply was refused by the bus: like a real drive, it does not retry."""
