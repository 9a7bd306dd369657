"""Several simulated drives sharing one bus, with the scheduler's machine shape."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

from abh3_supervisor.config.model import FaultKind, SimConfig, UnitConfig
from abh3_supervisor.core.robot import RobotConfig, from_geometry
from abh3_supervisor.params import table
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.protocol.ids import ADDR_ALL
from abh3_supervisor.simulator.drive import PULSES_PER_REV, SimDrive
from abh3_supervisor.simulator.robot import SimRobot, build


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

    def __init__(self, drives: Iterable[SimDrive], robots: Iterable[SimRobot] = ()) -> None:
        self.drives = {d.abh3_id: d for d in drives}
        self._due = {a: d.next_deadline() for a, d in self.drives.items()}
        # the robots whose wheels are all on this bus, as built (simulator/robot.py)
        self.robots = {r.name: r for r in robots}
        self._robots_of: dict[int, list[SimRobot]] = {}  # drive address → its robots
        for robot in self.robots.values():
            for address in dict.fromkeys(w.address for w in robot.wheels):
                self._robots_of.setdefault(address, []).append(robot)

    @classmethod
    def for_units(
        cls,
        units: Iterable[UnitConfig],
        cfg: SimConfig,
        now: float,
        bitrate: int | None = None,
        robots: Iterable[RobotConfig] | None = None,
    ) -> SimBus:
        """A drive per unit, set up as the file says (its parameter table follows the
        unit: see :func:`as_the_file_says`; its encoder counts the unit's
        ``geometry.pulses_per_rev``), but for ``cfg.params`` and ``cfg.faults``; and the
        ``robots`` (``Config.robots``; None: a one-drive robot per unit from its
        geometry) whose wheels are all on these units, built as the faults say."""
        units = list(units)

        def drive_cfg(u: UnitConfig) -> SimConfig:
            if cfg.command_zero_timeout_ms is not None:
                return cfg
            return replace(cfg, command_zero_timeout_ms=u.drive_timeout_ms)

        def generation(u: UnitConfig) -> Generation:
            wrong = any(
                f.kind is FaultKind.WRONG_PROTOCOL and f.unit in (None, u.name) for f in cfg.faults
            )
            if not wrong:
                return u.protocol
            return Generation.G2023 if u.protocol is Generation.G2021 else Generation.G2021

        addresses = {u.name: u.abh3_id for u in units}
        if robots is None:
            robots = [from_geometry(u.name, u.geometry) for u in units]
        robots = list(robots)
        here = [r for r in robots if all(w.unit in addresses for w in r.wheels)]
        # a robot's wheel gives the encoder's resolution where the unit's geometry does not
        ppr = {w.unit: w.pulses_per_rev for r in robots for w in r.wheels if w.pulses_per_rev}
        return cls(
            (
                SimDrive(
                    u.abh3_id,
                    group=u.brd_group,
                    generation=generation(u),
                    model=u.velocity_model,
                    cfg=drive_cfg(u),
                    now=now,
                    faults=tuple(f for f in cfg.faults if f.unit in (None, u.name)),
                    params={**as_the_file_says(u, bitrate), **cfg.params_of(u.name)},
                    accepts=cfg.forms_of(u.name),
                    pulses_per_rev=(u.geometry.pulses_per_rev or ppr.get(u.name) or PULSES_PER_REV),
                    time_constant_ms=cfg.time_constant_of(u.name),
                )
                for u in units
            ),
            (build(r, addresses, cfg.faults) for r in here),
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
            self._moved(drive.abh3_id)

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        out: list[tuple[int, bytes]] = []
        for address, due in self._due.items():
            if due <= now:
                drive = self.drives[address]
                out.extend(drive.poll(now))
                self._due[address] = drive.next_deadline()
                self._moved(address)
        return out

    def _moved(self, address: int) -> None:
        """The drive at ``address`` advanced: its robots take in what it turned."""
        for robot in self._robots_of.get(address, ()):
            robot.update(self.drives)

    def robot(self, name: str, now: float | None = None) -> SimRobot:
        """The simulated robot ``name``; given ``now``, its drives advanced to it first."""
        robot = self.robots[name]
        if now is not None:
            for w in robot.wheels:
                self.drives[w.address].advance(now)
            robot.update(self.drives)
        return robot

    def next_deadline(self) -> float:
        return min(self._due.values(), default=math.inf)

    def on_send_failed(self, arbitration_id: int) -> None:
        """A drive's reply was refused by the bus: like a real drive, it does not retry."""

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        """A drive ignores remote and FD frames."""
