"""``abh3 simulate``: the simulated drives of a file as a process of their own.

Each bus with ``simulate:`` gets its drives (every option, fault and wiring fault of the
file) on the bus the file names, so other processes — ``abh3 run``, ``tui``,
``commission``, ``param``, ``scan``, a listener — reach them as they would real drives.
Only a bus no real drive can be on is accepted (``udp_multicast``, a SocketCAN ``vcan``):
simulated drives answering on a real bus would lie to its host. The drives are told
what to do on standard input (simulator/control.py); what they do goes to ``--trace``
(simulator/watch.py) and the log; the frames they hear and send to ``--record``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

from abh3_supervisor.config.interfaces import shared_bus
from abh3_supervisor.config.model import Config
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.runtime import signals
from abh3_supervisor.runtime.bus_runtime import open_bus, simulator
from abh3_supervisor.runtime.recorder import GuardedRecorder, open_recorder
from abh3_supervisor.scheduler.pump import BusPump
from abh3_supervisor.simulator.control import obey
from abh3_supervisor.simulator.drive import SimDrive
from abh3_supervisor.simulator.watch import Watch

SAMPLE_S = 0.01  # the watch's period: a stop is placed within 10 ms
log = logging.getLogger(__name__)


def simulated_buses(config: Config, only: Iterable[str] = ()) -> list[str]:
    """The buses ``abh3 simulate`` runs: those with ``simulate:`` (or ``only`` those),
    each on an interface no real drive can be on — else an :class:`Abh3Error` saying why."""
    names = list(only) or [n for n, b in config.buses.items() if b.simulate is not None]
    if not names:
        raise Abh3Error("no bus of the file has `simulate:`: there are no drives to simulate")
    for name in names:
        bus = config.buses.get(name)
        if bus is None:
            raise Abh3Error(f"--bus {name}: no such bus (buses: {', '.join(config.buses)})")
        if bus.simulate is None:
            raise Abh3Error(f"bus '{name}' has no `simulate:`: its drives are real")
        if bus.interface == "virtual":
            raise Abh3Error(
                f"bus '{name}': python-can's virtual bus does not leave a process; for drives "
                "in a process of their own use `interface: udp_multicast` (channel "
                "239.74.163.2) or a SocketCAN vcan (docs/simulator.md)"
            )
        if not shared_bus(bus.interface, bus.channel):
            raise Abh3Error(
                f"bus '{name}': {bus.interface} {bus.channel} may carry real drives; "
                "`abh3 simulate` only puts drives on udp_multicast or a SocketCAN vcan"
            )
    return names


class Trace:
    """``--trace``: the watch's events as JSON lines, times on the wall clock."""

    def __init__(self, path: Path | None, offset: float) -> None:
        self.offset = offset  # wall clock − loop clock
        self._file: IO[str] | None = None
        self.path = path
        if path is not None:
            try:
                self._file = path.open("w", encoding="utf-8", buffering=1)
            except OSError as exc:
                raise Abh3Error(f"--trace {path}: cannot write: {exc.strerror}") from exc

    def write(self, events: Iterable[dict[str, Any]]) -> None:
        for event in events:
            wall = {
                k: self._wall(v) if k in ("t", "at", "last_command") else v
                for k, v in event.items()
            }
            if event["event"] != "state":
                log.info("%s", _said(wall))
            if self._file is not None:
                try:
                    self._file.write(json.dumps(wall) + "\n")
                except OSError as exc:  # a full disk: the trace ends, the drives go on
                    log.error("--trace %s: %s: the trace ends here", self.path, exc.strerror)
                    self._close_quietly()

    def _wall(self, t: object) -> object:
        return round(t + self.offset, 6) if isinstance(t, float) else t

    def close(self) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except OSError as exc:
                log.error("--trace %s: %s", self.path, exc.strerror)
            self._file = None

    def _close_quietly(self) -> None:
        file, self._file = self._file, None
        if file is not None:
            with contextlib.suppress(OSError):
                file.close()


def _said(event: dict[str, Any]) -> str:
    unit, kind = event["unit"], event["event"]
    if kind == "command_zero_timeout":
        return (
            f"{unit}: no command for {event['timeout_ms']} ms (0x4117): the drive stops "
            "its motors itself"
        )
    if kind == "standing":
        return f"{unit}: standing, {event['since_last_command_ms']} ms after the last command"
    if kind == "commanded":
        return f"{unit}: commanded again by host {event['host']}"
    return f"{unit}: {kind.replace('_', ' ')}"


async def simulate(
    config: Config,
    buses: list[str],
    *,
    trace: Path | None = None,
    record: Path | None = None,
    duration: float | None = None,
) -> int:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    recorder: GuardedRecorder | None = open_recorder(record, config) if record else None
    log_ = Trace(trace, time.time() - loop.time())
    drives: dict[str, SimDrive] = {}
    pumps: list[BusPump] = []
    opened = []
    try:
        for name in buses:
            cfg = config.buses[name]
            bus = open_bus(cfg)
            opened.append(bus)
            sim, pump = simulator(config, name, bus, loop.time(), recorder)
            units = config.units_on(name)
            drives.update({u.name: sim.drives[u.abh3_id] for u in units})
            pumps.append(pump)
            pump.start()
            who = ", ".join(f"{u.name} (abh3_id {u.abh3_id})" for u in units)
            print(f"ready: bus {name}: {who} on {cfg.interface} {cfg.channel}", flush=True)
        if recorder is not None:
            recorder.start_flushing(loop)
        watch = Watch(drives)
        sampler = loop.create_task(_sample(watch, log_))
        with (
            signals.on_loop(loop, lambda signum: stop.set()),
            _commands(drives, log_, stop),
            contextlib.suppress(TimeoutError),
        ):
            await asyncio.wait_for(stop.wait(), duration)
        sampler.cancel()
        log_.write(watch.sample(loop.time()))
    finally:
        for pump in pumps:
            pump.stop()
        if recorder is not None:
            recorder.stop()
        for bus in opened:
            bus.shutdown()
        log_.close()
    return 0


def _ours(fd: int) -> bool:
    if not os.isatty(fd):
        return True
    try:
        return os.tcgetpgrp(fd) == os.getpgrp()
    except OSError:  # no controlling terminal
        return False


async def _sample(watch: Watch, trace: Trace) -> None:
    loop = asyncio.get_running_loop()
    at = loop.time()
    while True:
        trace.write(watch.sample(loop.time()))
        at = max(at + SAMPLE_S, loop.time())
        await asyncio.sleep(at - loop.time())


@contextlib.contextmanager
def _commands(drives: dict[str, SimDrive], trace: Trace, stop: asyncio.Event) -> Iterator[None]:
    """Lines on standard input, when it is ours to read: a pipe, a file, or the terminal
    while in the foreground (a background job reading it would be stopped by the shell)."""
    loop = asyncio.get_running_loop()
    fd = sys.stdin.fileno() if sys.stdin is not None else -1
    if fd < 0 or not _ours(fd):
        yield
        return
    pending = b""

    def readable() -> None:
        nonlocal pending
        try:
            data = os.read(fd, 4096)
        except OSError:
            data = b""
        if not data:  # end of input: the drives go on until a signal
            loop.remove_reader(fd)
            return
        *lines, pending = (pending + data).split(b"\n")
        for raw in lines:
            answer = obey(raw.decode(errors="replace"), drives, loop.time())
            if answer.text:
                print(answer.text, flush=True)
            trace.write(answer.events)
            if answer.quit:
                stop.set()

    try:
        loop.add_reader(fd, readable)
    except (OSError, ValueError, NotImplementedError):  # a regular file: read it at once
        yield
        return
    try:
        yield
    finally:
        loop.remove_reader(fd)
