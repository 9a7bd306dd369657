"""A commissioning bench on a fake clock: the supervisor, the simulated drives and the
input arbitration on one :class:`Timeline`, so a whole sequence runs in milliseconds."""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from typing import TypeVar

from abh3_supervisor.commission.unit import Bench, RobotView
from abh3_supervisor.config import Config
from abh3_supervisor.core.inputs import InputArbiter, InputSource, Twist, VelocityYX
from abh3_supervisor.core.kinematics import ab_to_yx
from abh3_supervisor.core.verify import Verification
from abh3_supervisor.core.verifying import verify_units
from abh3_supervisor.params import table
from abh3_supervisor.params.telabh3 import Command
from abh3_supervisor.service.param_ops import ParamOps
from tests.support.rig import Rig

T = TypeVar("T")


class _Source(InputSource):
    def start(self, feed: object) -> None:
        pass

    def stop(self) -> None:
        pass


class _ArbiterMachine:
    """The arbitration's deadline (a lapsed command means zero) as a timeline node."""

    def __init__(self, arbiter: InputArbiter) -> None:
        self.arbiter = arbiter

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        pass

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        if self.arbiter.next_deadline() <= now:
            self.arbiter.poll(now)
        return []

    def next_deadline(self) -> float:
        return self.arbiter.next_deadline()

    def on_send_failed(self, arbitration_id: int) -> None:
        pass

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        pass


class FakeBench(Rig, Bench):
    def __init__(self, config: Config, timeout: float = 0.3) -> None:
        super().__init__(config, whole_robots=False)  # as `abh3 commission` runs
        self.arbiter = self.sup.arbiter
        for unit in config.units:
            self.arbiter.add(_Source(f"commission:{unit}", (unit,), priority=10, timeout=timeout))
        self.timeline.add(_ArbiterMachine(self.arbiter))
        self.ops = ParamOps(self.sup, lambda bus: None)
        self.stalled = False  # the sequence stops refreshing its command (a hung client)

    def now(self) -> float:
        return self.timeline.now

    async def wait(self, seconds: float) -> None:
        self.run(seconds)
        await asyncio.sleep(0)

    def move(self, unit: str, a: float, b: float) -> None:
        if not self.stalled:
            self.arbiter.submit(f"commission:{unit}", VelocityYX(*ab_to_yx(a, b)), self.now())

    def release(self, unit: str) -> None:
        self.arbiter.submit(f"commission:{unit}", None, self.now())

    def twist(self, unit: str, linear_x: float, angular_z: float) -> None:
        if not self.stalled:
            self.arbiter.submit(f"commission:{unit}", Twist(linear_x, angular_z), self.now())

    def wire(self) -> Sequence[tuple[float, int, bytes]]:
        return [(f.start, f.arbitration_id, f.data) for f in self.timeline.frames if f.node == 0]

    async def _stepping(self, job: asyncio.Future[T]) -> T:
        while not job.done():
            self.run(0.002)
            await asyncio.sleep(0)
        return job.result()

    async def identity(self, unit: str) -> str:
        job = asyncio.ensure_future(self.ops.identity(unit, table.FIRMWARE_VERSION))
        return await self._stepping(job)

    async def read_param(self, unit: str, address: int) -> int:
        job = asyncio.ensure_future(self.ops.read(unit, Command.PARAM, address))
        return await self._stepping(job)

    async def verification(self, unit: str) -> Verification:
        job = asyncio.ensure_future(verify_units(self.sup, [unit], act=False))
        return (await self._stepping(job))[unit]

    def sim_robot(self, name: str) -> RobotView | None:
        return self.sim.robots.get(name)


class Headless:
    """Says yes to every question and presses the e-stop when asked, at once; no terminal
    to choose a key or type a number on."""

    interactive = False

    def __init__(self, bench: FakeBench, answers: bool = True) -> None:
        self.bench, self.answers = bench, answers
        self.lines: list[str] = []

    async def choose(self, question: str, options: Sequence[tuple[str, str]]) -> str | None:
        self.lines.append(f"? {question}")
        return None

    async def measure(self, question: str) -> float | None:
        self.lines.append(f"? {question}")
        return None

    def say(self, text: str) -> None:
        self.lines.append(text)

    async def confirm(self, question: str) -> bool:
        self.lines.append(f"? {question}")
        return self.answers

    async def press_estop(self, prompt: str) -> float | None:
        t = self.bench.now()
        self.bench.sup.emergency_stop()
        return t
