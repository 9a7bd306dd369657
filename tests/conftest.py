"""Shared fixtures: fake-clock setups and a guard against leaked virtual buses."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import math
import os
import pty
import select
import shutil
import struct
import subprocess
import sys
import tempfile
import termios
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from can.interfaces import virtual

from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.config.model import SimConfig
from abh3_supervisor.core.inputs import InputFeed, InputSource
from abh3_supervisor.core.supervisor import Notice, Supervisor, SupervisorEvent
from abh3_supervisor.scheduler.pump import BusPump
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
        for unit in config.units:  # the test is the operator: its API commands stand
            self.sup.arbiter.add(_TestSource(f"api:{unit}", (unit,), timeout=math.inf))

    def run(self, seconds: float) -> None:
        self.timeline.run_until(self.timeline.now + seconds)

    def drive(self, unit: str):  # type: ignore[no-untyped-def]
        return self.sim.drives[self.config.units[unit].abh3_id]

    def own(self, unit: str) -> str:
        """A source present for the whole test that owns ``unit``'s motion (pass it as
        ``source=``): the API's own source is streamed and lapses after 0.5 s."""
        return present(self.sup, unit)


def present(sup: Supervisor, unit: str) -> str:
    """Register a test's input source for ``unit`` that never lapses; its name."""
    name = f"test:{unit}"
    if name not in sup.arbiter.sources:
        sup.arbiter.add(_TestSource(name, (unit,), timeout=math.inf))
    return name


class _TestSource(InputSource):
    def start(self, feed: InputFeed) -> None:
        pass

    def stop(self) -> None:
        pass


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


def in_a_terminal(args: list[str]) -> tuple[int, int]:
    """``abh3 ARGS`` on a pseudo-terminal, once its screen shows both units online."""
    pid, fd = pty.fork()
    if pid == 0:
        os.chdir(Path(__file__).resolve().parent.parent)
        os.execv(sys.executable, [sys.executable, "-m", "abh3_supervisor", *args])
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 180, 0, 0))
    screen = b""
    while screen.count(b"online") < 2:
        ready, _, _ = select.select([fd], [], [], 30)
        assert ready, f"no TUI output: {screen[-500:]!r}"
        screen += os.read(fd, 65536)
    return pid, fd


def assert_demo_stopped(record: Path) -> None:
    """The last DP0 command to each of configs/demo.yaml's drives (a 2021 at 1, a 2023 at
    3, host 2) in a ``--record`` file is the stop: zero and the safe word."""
    from abh3_supervisor.protocol import flags, frames, ids

    layouts = {1: flags.LAYOUT_2021, 3: flags.LAYOUT_2023}
    last = {}
    for msg in can.LogReader(str(record)):
        for abh3, lay in layouts.items():
            if msg.arbitration_id == ids.dp0_command_id(abh3, 2):
                last[abh3] = frames.decode_dp0_command(bytes(msg.data), lay.generation)
    assert len(last) == 2
    for abh3, cmd in last.items():
        assert isinstance(cmd, frames.Dp0Command) and (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0)
        assert cmd.inputs & ~layouts[abh3].select_mask == 0  # the safe word


@dataclass
class HeadlessRun:
    """What a headless run logged after both units came online (filled when it ends)."""

    log: str = ""


@contextlib.contextmanager
def headless_demo(sock: Path) -> Iterator[HeadlessRun]:
    """``abh3 run configs/demo.yaml --headless`` serving ``sock`` in a process of its own,
    entered once both units are online; on leaving, SIGTERM, and it must exit 0."""
    serve = ["--headless", "--socket", str(sock), "--status-interval", "0"]
    run = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", "configs/demo.yaml", *serve],
        stderr=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).resolve().parent.parent,
    )
    assert run.stderr is not None
    served = HeadlessRun()
    try:
        for line in run.stderr:
            if "unit right: online" in line:  # serving starts before: both are up now
                break
        yield served
    finally:
        run.terminate()
        served.log = run.stderr.read()
        assert run.wait(30) == 0, served.log


class FillsUp:
    """A raw file that takes ``room`` more bytes, then reports the disk full (as write(2)
    does: a short write first, then ENOSPC)."""

    def __init__(self, real: Any, room: int) -> None:
        self.real, self.room = real, room

    def write(self, data: bytes) -> int:
        if self.room <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        part = bytes(data[: self.room])
        self.room -= len(part)
        return int(self.real.write(part))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.real, name)
