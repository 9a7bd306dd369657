"""Buses, pumps, simulators and the supervisor, started and stopped together.

``async with Runtime(config) as rt:`` opens every bus, attaches simulators, and starts the
schedulers; leaving the block by any path (normal end, Ctrl-C, SIGTERM, an exception)
sends every commanded unit its stop frame (zero, the safe word: SERVO, START, brake and
every other switch off), repeated until the drive reports SERVO and START off, for at
most ``STOP_DEADLINE_S`` (runtime/stopping.py), whatever else fails (a recorder, a
plugin, a UI); then the recording and the buses are closed. :attr:`Runtime.stop_report`
says per unit what became of its stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import logging
import math
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Any

import can

from abh3_supervisor.config.endpoint import Endpoint
from abh3_supervisor.config.interfaces import echoes_own_frames, unknown_interface
from abh3_supervisor.config.model import BusConfig, Config, FaultKind, SimConfig
from abh3_supervisor.core import verify, verifying
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import BusOpenError, PluginError
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime import priority
from abh3_supervisor.runtime.echo import without_own_frames
from abh3_supervisor.runtime.foxglove_live import FoxgloveLive, start_foxglove
from abh3_supervisor.runtime.recorder import GuardedRecorder, open_recorder
from abh3_supervisor.runtime.stopping import CONFIRMED, stop_drives
from abh3_supervisor.scheduler.core import BusScheduler
from abh3_supervisor.scheduler.pump import READ_BATCH_S, BusPump
from abh3_supervisor.scheduler.timer import DeadlineTimer
from abh3_supervisor.simulator.bus import SimBus
from abh3_supervisor.simulator.local_bus import LocalBus

log = logging.getLogger(__name__)


def open_bus(cfg: BusConfig, *, from_file: bool = True, doorbell: bool | None = None) -> can.BusABC:
    """The bus, or a :class:`BusOpenError` naming the real cause and what to do.

    ``from_file``: the bus comes from a YAML file (a hint may name its keys); ``abh3 scan``
    gives it on the command line, where the file's keys mean nothing. ``doorbell``: the
    in-process simulator's bus (simulator/local_bus.py) — True its drives' side, False
    the supervisor's."""
    if (problem := unknown_interface(cfg.interface)) is not None:  # typed by hand
        raise BusOpenError(_cannot_open(cfg, problem))
    kwargs: dict[str, Any] = {"bitrate": cfg.bitrate, **cfg.options}
    try:
        if doorbell is not None:
            bus: can.BusABC = LocalBus(cfg.channel, doorbell=doorbell, **kwargs)
        else:
            bus = can.Bus(interface=cfg.interface, channel=cfg.channel, **kwargs)
        # no code of ours may see its own frames: on udp_multicast it would take its own
        # commands for another host's (runtime/echo.py)
        if echoes_own_frames(cfg.interface, cfg.options):
            bus = _without_own_frames(bus, cfg)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        hint = _socketcan_hint(cfg, exc, from_file) if cfg.interface == "socketcan" else ""
        raise BusOpenError(_cannot_open(cfg, f"{exc}{hint}")) from exc
    return bus


def _without_own_frames(bus: can.BusABC, cfg: BusConfig) -> can.BusABC:
    try:
        return without_own_frames(bus, cfg.interface, cfg.channel)
    except BaseException:
        bus.shutdown()
        raise


def _cannot_open(cfg: BusConfig, why: str) -> str:
    return f"bus '{cfg.name}': cannot open {cfg.interface} channel '{cfg.channel}': {why}"


def _errno(exc: BaseException) -> int | None:
    """The OS error number behind an exception python-can raised (it may wrap it)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        number = getattr(current, "errno", None) or getattr(current, "error_code", None)
        if isinstance(number, int):
            return number
        current = current.__cause__ or current.__context__
    return None


def _socketcan_hint(cfg: BusConfig, exc: BaseException, from_file: bool) -> str:
    def interface(name: str) -> str:
        return f"`interface: {name}`" if from_file else f"`--interface {name}`"

    simulate = "; or add `simulate: true` to the bus to run it on the simulator"
    if _errno(exc) == errno.EAFNOSUPPORT:  # no AF_CAN: not a device, the kernel itself
        return (
            ": this kernel has no SocketCAN at all (no CAN address family, whatever the "
            "device): load it with `sudo modprobe can can_raw` (the kernel must be built "
            "with CONFIG_CAN), or use an interface that needs no SocketCAN, such as the "
            f"drive maker's USB-CAN adapter ({interface('wacousb')}, channel /dev/ttyACM0) "
            f"or an slcan adapter ({interface('slcan')})" + (simulate if from_file else "")
        )
    return (
        f" (is the interface up? e.g. `sudo ip link set {cfg.channel} up type can "
        f"bitrate {cfg.bitrate}`" + (simulate if from_file else "") + ")"
    )


def in_process(cfg: BusConfig) -> bool:
    """Whether the runtime simulates this bus's drives itself (on the virtual bus), not
    ``abh3 simulate`` in another process (``simulate.external``) or real drives."""
    return cfg.simulate is not None and not cfg.simulate.external


def as_opened(cfg: BusConfig) -> BusConfig:
    """The bus the runtime really opens for ``cfg`` (see :func:`simulated`)."""
    return simulated(cfg) if in_process(cfg) else cfg


def simulated(cfg: BusConfig) -> BusConfig:
    """The bus a simulated one really runs on: python-can's in-process ``virtual`` bus,
    whatever the file's interface — ``simulate: true`` means "instead of real drives", so
    the file of a real robot runs on the simulator as written (no can0 needed). The
    interface must still be one python-can knows (the file is meant for the robot too):
    the file's check refuses any other, and so does this, for a configuration built in
    code."""
    if cfg.interface == "virtual":
        return cfg
    if (problem := unknown_interface(cfg.interface)) is not None:  # a typo is wrong either way
        raise BusOpenError(_cannot_open(cfg, problem))
    log.info(
        "bus %s: simulated: on python-can's virtual bus instead of %s %s",
        cfg.name,
        cfg.interface,
        cfg.channel,
    )
    return replace(cfg, interface="virtual", options={})


def simulator(
    config: Config, name: str, bus: can.BusABC, now: float, recorder: can.Listener | None = None
) -> tuple[SimBus, BusPump]:
    """Bus ``name``'s simulated drives, set up as the file says (``SimBus.for_units``),
    and the pump that runs them on ``bus`` — in the supervisor's process or in ``abh3
    simulate``'s; the caller starts the pump."""
    cfg = config.buses[name]
    assert cfg.simulate is not None, f"bus {name} is not simulated"
    sim = SimBus.for_units(
        config.units_on(name), cfg.simulate, now, bitrate=cfg.bitrate, robots=config.robots.values()
    )
    pump = BusPump(bus, sim, name=f"{name} (simulator)", channel=cfg.channel, recorder=recorder)
    return sim, pump


def _refuse_in_fault_windows(
    bus: can.BusABC, sim: SimConfig | None, loop: asyncio.AbstractEventLoop
) -> None:
    """The simulator's scripted ``bus_send_error`` windows: the host's bus refuses to send
    in them, as a real interface does (the pump's usual send-error path handles it)."""
    windows = [f for f in (sim.faults if sim else ()) if f.kind is FaultKind.BUS_SEND_ERROR]
    if not windows:
        return
    start, send = loop.time(), bus.send

    def refusing(msg: can.Message, timeout: float | None = None) -> None:
        if any(f.active(loop.time() - start) for f in windows):
            raise can.CanOperationError("simulated fault: the bus refuses to send")
        send(msg, timeout)

    bus.send = refusing  # type: ignore[method-assign]


class Runtime:
    def __init__(
        self,
        config: Config,
        *,
        record: Path | None = None,
        plugins: PluginHost | None = None,
        foxglove: Endpoint | None = None,
        whole_robots: bool = True,
    ) -> None:
        self.config = config
        self.whole_robots = whole_robots  # off for commissioning: one wheel at a time
        self.record = record
        self.live = foxglove  # where to serve the live view: `abh3 run`'s, not every tool's
        self.plugins = plugins
        self.supervisor: Supervisor
        self.sims: dict[str, SimBus] = {}
        self.pumps: dict[str, BusPump] = {}
        self._sim_pumps: list[BusPump] = []
        self._buses: list[can.BusABC] = []
        self._recorder: GuardedRecorder | None = None
        self.recording: GuardedRecorder | None = None  # the same, kept once closed: its outcome
        self.foxglove: FoxgloveLive | None = None  # the live view (`foxglove:`), when asked
        self.fatal: asyncio.Future[object] | None = None
        self.ended = asyncio.Event()  # a plugin ended the run (a normal stop, exit 0)
        self.stop_report: dict[str, str] = {}  # unit → CONFIRMED, SENT or "NOT sent: …"
        # the start-up check of the drives' CAN settings (core/verify.py), while it runs
        self.verifying: asyncio.Task[dict[str, verify.Verification]] | None = None
        self._timer: DeadlineTimer | None = None

    async def __aenter__(self) -> Runtime:
        loop = asyncio.get_running_loop()
        self.fatal = loop.create_future()
        try:
            self._start(loop)
        except BaseException:
            try:
                if self.plugins is not None and self.plugins.started:
                    self.plugins.stop(self.supervisor)  # those that started get abh3_stop
            finally:
                self._close()
            raise
        return self

    def _start(self, loop: asyncio.AbstractEventLoop) -> None:
        # the live view first: a port taken exits 2 before the recording's file is opened
        # (and so emptied) and before any bus opens
        if self.live is not None:
            self.foxglove = start_foxglove(self.live, f"abh3 {self.config.file}")
        if self.record is not None:
            self._recorder = self.recording = open_recorder(self.record, self.config)
            self._recorder.start_flushing(loop)  # a kill -9 loses at most FLUSH_S
        self.supervisor = Supervisor(self.config, clock=loop.time, whole_robots=self.whole_robots)
        self.supervisor.call_at = loop.call_at
        self._arbitrate(loop)
        attach = getattr(self._recorder.writer if self._recorder else None, "attach", None)
        if self._recorder is not None and attach is not None:  # decoded values too (MCAP)
            attach(self.supervisor, loop.time)
            self.supervisor.subscribe(self._recorder.observe)
        listener: can.Listener | None = self._recorder  # what the pumps hand every frame
        if self.foxglove is not None:  # the recording's topics, live
            listener = feed = self.foxglove.feed(self._recorder, self.config)
            feed.attach(self.supervisor, loop.time)
            self.supervisor.subscribe(feed.observe)
        for name, cfg in self.config.buses.items():
            if (sim_cfg := cfg.simulate) is not None and not in_process(cfg):
                log.info(
                    "bus %s: its drives are simulated in another process (`abh3 simulate`): "
                    "opening %s %s as a real bus",
                    name,
                    cfg.interface,
                    cfg.channel,
                )
            elif sim_cfg is not None:
                cfg = simulated(cfg)
                # the drives' bus rings when ours sends: their pump steps right after ours
                sim_bus = open_bus(cfg, doorbell=True)
                self._buses.append(sim_bus)
                self.sims[name], pump = simulator(self.config, name, sim_bus, loop.time())
                self._sim_pumps.append(pump)
                pump.start()
            bus = open_bus(cfg, doorbell=False if in_process(cfg) else None)
            self._buses.append(bus)
            _refuse_in_fault_windows(bus, cfg.simulate, loop)
            scheduler = self.supervisor.schedulers[name]
            self.pumps[name] = BusPump(
                bus,
                scheduler,
                name=name,
                channel=cfg.channel,
                after_step=functools.partial(self.supervisor.dispatch, name),
                recorder=listener,
                on_fatal=self._on_fatal,
                health=self.supervisor.bus_health[name],
                batch_s=READ_BATCH_S,  # a frame waits for the next step if one is near
                turns=scheduler,  # a turn's replies: read by the next turn
            )
        if self.plugins is not None:  # before any frame: a plugin that cannot start

            def request_stop(why: str) -> None:  # from a plugin's worker thread
                # a plugin left behind may fail after the run: the loop is gone, nothing to end
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(self._on_fatal, PluginError(why))

            self.plugins.request_stop = request_stop

            def end_run(why: str) -> None:  # a plugin is done (its view's end_run): exit 0
                loop.call_soon_threadsafe(self.ended.set)

            self.plugins.end_run = end_run
            # plugins' threads (DDS, rclpy's executor) at normal priority: at the loop's
            # real-time one they delayed rclpy's cmd_vel by 150–250 ms; just below it for
            # a plugin that asks (runtime/priority.py)
            self.plugins.thread_setup = priority.plugin_thread
            self.plugins.demote = priority.demote
            self.plugins.start(self.supervisor, loop)  # fails the run before motion
        for name, pump in self.pumps.items():
            self.supervisor.wakers[name] = pump.wake
            scheduler = self.supervisor.schedulers[name]
            self.supervisor.senders(name, functools.partial(_send_now, pump, scheduler))
            pump.start()
        # the drives' CAN settings against the file, in the background (core/verify.py):
        # a `verify: refuse` unit's start-up commands wait for it
        verifying.announce_forms(self.supervisor)
        waiting, self.verifying = verifying.begin(self.supervisor)
        for name in self.config.units:
            if name not in waiting:
                verifying.run_startup(self.supervisor, name)

    def _arbitrate(self, loop: asyncio.AbstractEventLoop) -> None:
        """The arbitration's deadline timer: a silent source's units get zero the moment
        its timeout passes, not at the next frame (core/inputs.py)."""
        arbiter = self.supervisor.arbiter
        timer = self._timer = DeadlineTimer(loop, lambda: arbiter.poll(loop.time()))

        def rearm() -> None:
            deadline = arbiter.next_deadline()
            if math.isfinite(deadline):
                timer.arm(deadline)
            else:
                timer.cancel()

        arbiter.on_change = rearm

    def _on_fatal(self, exc: BaseException) -> None:
        if self.fatal is not None and not self.fatal.done():
            self.fatal.set_result(exc)

    async def __aexit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self.verifying is not None:
            self.verifying.cancel()  # its requests leave the channels; no start-up after
        try:
            self.supervisor.arbiter.closed = True  # nothing may command motion from here on
            if self._timer is not None:
                self._timer.close()
            if self.plugins is not None:
                try:
                    self.plugins.stop_inputs()
                except Exception:  # never a reason not to stop the drives
                    log.exception("stopping the inputs failed; stopping the drives anyway")
            # the normal way out is a controlled stop; an error ends with the safe word now
            failed = et is not None or (self.fatal is not None and self.fatal.done())
            await self.stop_drives(0.0 if failed else self.config.stop_ramp_s)
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
        ended: asyncio.Future[object] = asyncio.ensure_future(self.ended.wait())
        try:
            await asyncio.wait(
                [stopped, ended, self.fatal], timeout=timeout, return_when=asyncio.FIRST_COMPLETED
            )
        finally:
            stopped.cancel()
            ended.cancel()

    @property
    def stops_confirmed(self) -> bool:
        return all(outcome == CONFIRMED for outcome in self.stop_report.values())

    async def stop_drives(self, ramp_s: float = 0.0) -> None:
        """The stop path (:mod:`.stopping`); the outcome per unit in :attr:`stop_report`."""
        self.stop_report = await stop_drives(self.supervisor, self.pumps, ramp_s)

    def _close(self) -> None:
        for pump in [*self.pumps.values(), *self._sim_pumps]:
            pump.stop()
        if self._recorder is not None:
            self._recorder.stop()  # after the stop frames: flushed and closed
            self._recorder = None
        if self.foxglove is not None:
            self.foxglove.stop()  # after the stop frames: viewers saw them
            self.foxglove = None
        for bus in self._buses:
            bus.shutdown()
        self._buses.clear()


def _send_now(pump: BusPump, scheduler: BusScheduler, unit: str) -> None:
    """``unit``'s frame on ``pump``'s bus now, outside its schedule (the e-stop's)."""
    pump.send(*scheduler.send_now(unit, pump.loop.time()))
