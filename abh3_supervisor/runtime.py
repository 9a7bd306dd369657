"""Buses, pumps, simulators and the supervisor, started and stopped together.

``async with Runtime(config) as rt:`` opens every bus, attaches simulators, and starts the
schedulers; leaving the block by any path (normal end, Ctrl-C, SIGTERM, an exception)
commands zero with START and SERVO off on every unit, waits briefly for the drives to
answer that frame, then closes the recording and the buses.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import signal
from pathlib import Path
from types import TracebackType
from typing import Any

import can

from abh3_supervisor.config.model import BusConfig, Config
from abh3_supervisor.errors import BusOpenError
from abh3_supervisor.plugin_host import PluginHost
from abh3_supervisor.scheduler.pump import BusPump
from abh3_supervisor.simulator.bus import SimBus
from abh3_supervisor.supervisor import Supervisor

log = logging.getLogger(__name__)
STOP_CONFIRM_S = 0.5  # longest wait for the drives to answer the stop frame
# every signal that ends the program normally: Ctrl-C, kill, and the terminal going away
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def open_bus(cfg: BusConfig) -> can.BusABC:
    kwargs: dict[str, Any] = {"bitrate": cfg.bitrate, **cfg.options}
    try:
        return can.Bus(interface=cfg.interface, channel=cfg.channel, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        hint = ""
        if cfg.interface == "socketcan":
            hint = (
                f" (is the interface up? e.g. `sudo ip link set {cfg.channel} up type can "
                f"bitrate {cfg.bitrate}`; or use `simulate: true` with interface: virtual)"
            )
        raise BusOpenError(
            f"bus '{cfg.name}': cannot open {cfg.interface} channel '{cfg.channel}': {exc}{hint}"
        ) from exc


def open_recorder(path: Path) -> can.Listener:
    try:
        return can.Logger(str(path))  # format from the extension: .log .asc .blf .csv …
    except ValueError as exc:
        raise BusOpenError(f"--record {path}: {exc} (use .log, .asc, .blf or .csv)") from exc
    except OSError as exc:
        raise BusOpenError(f"--record {path}: cannot write: {exc.strerror}") from exc


class Runtime:
    def __init__(
        self, config: Config, *, record: Path | None = None, plugins: PluginHost | None = None
    ) -> None:
        self.config = config
        self.record = record
        self.plugins = plugins
        self.supervisor: Supervisor
        self.sims: dict[str, SimBus] = {}
        self.pumps: dict[str, BusPump] = {}
        self._sim_pumps: list[BusPump] = []
        self._buses: list[can.BusABC] = []
        self._recorder: can.Listener | None = None
        self.fatal: asyncio.Future[object] | None = None

    async def __aenter__(self) -> Runtime:
        loop = asyncio.get_running_loop()
        self.fatal = loop.create_future()
        try:
            self._start(loop)
        except BaseException:
            self._close()
            raise
        return self

    def _start(self, loop: asyncio.AbstractEventLoop) -> None:
        if self.record is not None:
            self._recorder = open_recorder(self.record)
        self.supervisor = Supervisor(self.config, clock=loop.time)
        for name, cfg in self.config.buses.items():
            if cfg.simulate is not None:
                sim_bus = open_bus(cfg)
                self._buses.append(sim_bus)
                sim = SimBus.for_units(self.config.units_on(name), cfg.simulate, loop.time())
                self.sims[name] = sim
                pump = BusPump(sim_bus, sim, name=f"{name} (simulator)", channel=cfg.channel)
                self._sim_pumps.append(pump)
                pump.start()
            bus = open_bus(cfg)
            self._buses.append(bus)
            self.pumps[name] = BusPump(
                bus,
                self.supervisor.schedulers[name],
                name=name,
                channel=cfg.channel,
                after_step=functools.partial(self.supervisor.dispatch, name),
                recorder=self._recorder,
                on_fatal=self._on_fatal,
            )
        for name, pump in self.pumps.items():
            self.supervisor.wakers[name] = pump.wake
            pump.start()
        if self.plugins is not None:
            self.plugins.start(self.supervisor, loop)
        for name, unit in self.config.units.items():
            for text in unit.startup:  # validated when the file loaded
                response = self.supervisor.apply_text(name, text)
                log.info("unit %s: startup %r → %r", name, text, response)

    def _on_fatal(self, exc: BaseException) -> None:
        if self.fatal is not None and not self.fatal.done():
            self.fatal.set_result(exc)

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if self.plugins is not None:
                self.plugins.stop_inputs()  # nothing may command motion from here on
            await self.stop_drives()
        finally:
            try:
                if self.plugins is not None:
                    self.plugins.stop(self.supervisor)  # recordings get their last rows
            finally:
                self._close()

    async def run_until(self, stop: asyncio.Event, timeout: float | None = None) -> None:
        """Run until ``stop`` is set, an internal error ends the run (see :attr:`fatal`),
        or ``timeout`` seconds pass."""
        assert self.fatal is not None, "only inside `async with Runtime(...)`"
        stopped: asyncio.Future[object] = asyncio.ensure_future(stop.wait())
        try:
            await asyncio.wait(
                [stopped, self.fatal], timeout=timeout, return_when=asyncio.FIRST_COMPLETED
            )
        finally:
            stopped.cancel()

    async def stop_drives(self) -> None:
        """Zero, START and SERVO off on every commanded unit, sent now and confirmed."""
        sup = self.supervisor
        sup.safe_state()
        loop = asyncio.get_running_loop()
        since = loop.time()
        waits: dict[str, asyncio.Future[bool]] = {}
        for bus, scheduler in sup.schedulers.items():
            pump = self.pumps.get(bus)
            if pump is None:
                continue
            for name, slot in scheduler.slots.items():
                if slot.commanding and slot.online:
                    waits[name] = sup.expect_exchange(name, since)
            for arbitration_id, data in scheduler.flush(since):
                pump.send(arbitration_id, data)
        if not waits:
            return
        _, pending = await asyncio.wait(waits.values(), timeout=STOP_CONFIRM_S)
        for name, future in waits.items():
            if future in pending:
                future.cancel()
                log.warning("unit %s: stop frame sent, not confirmed by the drive", name)
            else:
                log.info("unit %s: stop frame confirmed by the drive", name)

    def _close(self) -> None:
        for pump in [*self.pumps.values(), *self._sim_pumps]:
            pump.stop()
        if self._recorder is not None:
            self._recorder.stop()  # flushes and closes the file: no lost recording
            self._recorder = None
        for bus in self._buses:
            bus.shutdown()
        self._buses.clear()
