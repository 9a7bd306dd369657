"""Several simulated drives sharing one bus, with the scheduler's machine shape."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

from abh3_supervisor.config.model import SimConfig, UnitConfig
from abh3_supervisor.params import table
from abh3_supervisor.protocol.ids import ADDR_ALL
from abh3_supervisor.simulator.drive import PULSES_PER_REV, SimDrive


def as_the_file_says(unit: UnitConfig, bitrate: int | None) -> dict[int, int]:
    """The parameter words a drive set up as ``unit`` says has beyond what the drive knows
    of itself (its address, group and timeouts: :class:`SimDrive`): its host address and
    the bus's bitrate, in kbit/s as the table's default is (None: that default, 500)."""
    words = {0x4103: table.to_word(unit.host_id, "pf")}
    if bitrate is not None:
        words[0x4101] = table.to_word(bitrate // 1000, "pf")
    return words


class SimBus:
    """Routes each frame to the drive it addresses and polls only drives that are due.

    Per frame and per step the cost is that of the drives involved, not of all of them:
    a bus with many simulated drives stays cheap to run.
    """

    def __init__(self, drives: Iterable[SimDrive]) -> None:
        self.drives = {d.abh3_id: d for d in drives}
        self._due = {a: d.next_deadline() for a, d in self.drives.items()}

    @classmethod
    def for_units(
        cls, units: Iterable[UnitConfig], cfg: SimConfig, now: float, bitrate: int | None = None
    ) -> SimBus:
        """A drive per unit, set up as the file says (its parameter table follows the
        unit: see :func:`as_the_file_says`; its encoder counts the unit's
        ``geometry.pulses_per_rev``), but for ``cfg.params`` and ``cfg.faults``."""

        def drive_cfg(u: UnitConfig) -> SimConfig:
            if cfg.command_zero_timeout_ms is not None:
                return cfg
            return replace(cfg, command_zero_timeout_ms=u.drive_timeout_ms)

        return cls(
            SimDrive(
                u.abh3_id,
                group=u.brd_group,
                generation=u.protocol,
                model=u.velocity_model,
                cfg=drive_cfg(u),
                now=now,
                faults=tuple(f for f in cfg.faults if f.unit in (None, u.name)),
                params={**as_the_file_says(u, bitrate), **cfg.params_of(u.name)},
                accepts=cfg.forms_of(u.name),
                pulses_per_rev=u.geometry.pulses_per_rev or PULSES_PER_REV,
                time_constant_ms=cfg.time_constant_of(u.name),
            )
            for u in units
        )

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        destination = arbitration_id >> 8 & 0xFF  # PS: the addressed drive, or all
        if destination == ADDR_ALL:
            targets = list(self.drives.values())
        elif (drive := self.drives.get(destination)) is not None:
            targets = [drive]
        else:
            return
        for drive in targets:
            drive.on_frame(arbitration_id, data, now)
            self._due[drive.abh3_id] = drive.next_deadline()

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        out: list[tuple[int, bytes]] = []
        for address, due in self._due.items():
            if due <= now:
                drive = self.drives[address]
                out.extend(drive.poll(now))
                self._due[address] = drive.next_deadline()
        return out

    def next_deadline(self) -> float:
        return min(self._due.values(), default=math.inf)

    def on_send_failed(self, arbitration_id: int) -> None:
        """A drive's reply was refused by the bus: like a real drive, it does not retry."""

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        """A drive ignores remote and FD frames."""
