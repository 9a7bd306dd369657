"""A source's thread-safe feed (:class:`InputFeed`): what an input source calls from its
own threads, handed to the event loop, where the supervisor's arbitration
(core/inputs.py) decides who owns each unit's motion. It lives with the plugin host, which
starts the sources and gives each its feed: the core has no threads and no clock."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import numbers
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any

from abh3_supervisor.core.commands import RESPONSE_INVALID, CurrentCommand, VelocityCommand
from abh3_supervisor.core.inputs import (
    CommandOutcome,
    InputArbiter,
    InputCommand,
    Motion,
    Twist,
    VelocityYX,
    execute,
)
from abh3_supervisor.core.kinematics import ab_to_yx
from abh3_supervisor.core.readiness import SETTLE_S
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.core.text import clean
from abh3_supervisor.errors import CommandError

REFUSED_NOTICE_S = 1.0  # a source's invalid values are said at most once in this


class InputFeed:
    """A source's thread-safe :class:`Feed`: every call is handed to the event loop.

    Besides the arbitrated motion commands, a source may change input bits, run the
    command language and ask for status packets on its units (the seed's ``inp_data``,
    ``inp_service`` and ``brd_num``): these are not arbitrated, they act at once.

    A motion value that is not a finite real number (NaN, inf, ``'100'``, None) is
    refused here, with a notice naming the source (at most one per ``REFUSED_NOTICE_S``):
    it is not a command, so the source's previous one lapses at its timeout and its
    units stop, exactly as when the source is silent.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        arbiter: InputArbiter,
        name: str,
        supervisor: Supervisor,
    ) -> None:
        self._loop, self._arbiter, self._name, self._sup = loop, arbiter, name, supervisor
        self._refusals = threading.Lock()  # a source may call from several threads
        self._refused = 0  # invalid values not yet said
        self._said = -math.inf  # when they were last said (monotonic)

    def twist(self, linear_x: float, angular_z: float) -> None:
        if (v := self._valid("twist", linear_x, angular_z)) is not None:
            self._submit(Twist(*v))

    def velocity_ab(self, a: float, b: float) -> None:
        """Motor-axis velocities A/B [min⁻¹], converted to each unit's model (Y/X, which
        a motor-model unit turns back into A/B)."""
        if (v := self._valid("velocity_ab", a, b)) is not None:
            self._submit(VelocityYX(*ab_to_yx(*v)))

    def velocity_yx(self, y: float, x: float) -> None:
        if (v := self._valid("velocity_yx", y, x)) is not None:
            self._submit(VelocityYX(*v))

    def velocity(self, ay: float, bx: float) -> None:
        if (v := self._valid("velocity", ay, bx)) is not None:
            self._submit(VelocityCommand(*v))

    def current(self, ay: float, bx: float) -> None:
        if (v := self._valid("current", ay, bx)) is not None:
            self._submit(CurrentCommand(*v))

    def _valid(self, what: str, *values: object) -> tuple[float, float] | None:
        """The values as floats, or None (refused: said, at most once a second)."""
        if all(
            isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
            for v in values
        ):
            return _real(values[0]), _real(values[1])
        shown = ", ".join(clean(repr(v))[:40] for v in values)
        self._refuse(
            f"{what}({shown}): not finite numbers; its units stop at its timeout as if it "
            "were silent"
        )
        return None

    def _refuse(self, why: str) -> None:
        """A call refused: said as a notice naming the source, at most once a second."""
        with self._refusals:
            self._refused += 1
            now = time.monotonic()
            if now - self._said < REFUSED_NOTICE_S:
                return
            count, self._refused, self._said = self._refused, 0, now
        more = f" ({count - 1} more refused since the last notice)" if count > 1 else ""
        message = f"input {self._name} refused: {why}{more}"
        with contextlib.suppress(RuntimeError):  # the loop closed: the run is over
            self._loop.call_soon_threadsafe(self._sup.notice, None, logging.WARNING, message)

    def release(self) -> None:
        """The source lets go (deadman released, device lost): its units stop now."""
        self._submit(None)

    def emergency_stop(self) -> None:
        """Latch the e-stop on every unit (not only this source's), from any thread: each
        commanded unit's stop frame goes out at once (docs/safety.md). Always honoured,
        even once the inputs have stopped."""
        if not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._sup.emergency_stop, f"input {self._name}")

    def retarget(self, units: tuple[str, ...]) -> None:
        """Drive other units from now on; units left behind stop if this source drove them.
        Names that are not this configuration's units are refused (nothing changes): a
        unit the arbitration cannot decide would keep what it was last given."""
        known = self._sup.units
        if not isinstance(units, tuple | list) or not all(
            isinstance(u, str) and u in known for u in units
        ):
            self._refuse(f"retarget({clean(repr(units))[:80]}): not a list of its units")
            return
        self._on_loop(self._arbiter.retarget_now, self._name, tuple(units))

    def inputs(self, data: int, mask: int) -> None:
        """Set the input bits selected by ``mask`` (uint32) to those of ``data``."""
        self._on_loop(self._each, self._sup.set_inputs, data & 0xFFFFFFFF, mask & 0xFFFFFFFF)

    def request_status(self, packet: int) -> None:
        """Ask for broadcast ``packet`` (0–6) once; it arrives through ``abh3_status``."""
        self._on_loop(self._each, self._sup.request_status, packet)

    def command(self, text: str) -> concurrent.futures.Future[str]:
        """Run a command-language string on the source's units; the future holds the
        seed's response (``''``, ``'Invalid Command.'`` or ``'Packet Error: n'``) once a
        drive answered or the unit's timeout passed. The first unit that fails answers.
        A ``VEL``/``CUR`` is this source's motion like any other it submits: fresh for its
        timeout, so it must be repeated to hold (an owner who is present)."""

        async def run() -> str:
            if self._arbiter.closed:
                return RESPONSE_INVALID
            return (await self.execute(text, standing=False)).response

        return self._answered(run)

    def _answered(
        self, run: Callable[[], Coroutine[Any, Any, str]]
    ) -> concurrent.futures.Future[str]:
        """``run()`` on the loop, its answer in a future for the source's thread; the
        seed's ``Invalid Command.`` at once once the loop is gone."""
        if self._loop.is_closed():
            future: concurrent.futures.Future[str] = concurrent.futures.Future()
            future.set_result(RESPONSE_INVALID)
            return future
        return asyncio.run_coroutine_threadsafe(run(), self._loop)

    def enable(self, on: bool) -> concurrent.futures.Future[str]:
        """Switch the robot(s) of the source's units on (``on``) or off as one act
        (``Supervisor.enable``); the future holds ``''`` once every drive reports it (or
        off), else why not, naming the drive: ``refused: …`` or ``not ready: …``."""

        async def run() -> str:
            if self._arbiter.closed:
                return "refused: the supervisor is stopping: commands are refused"
            sup = self._sup
            units = self._units()
            try:
                robots = {sup.robot(u).name: sup.robot(u).units[0] for u in units}
                for robot in robots:
                    sup.enable(robot, on, self._name)
            except CommandError as exc:
                return f"refused: {exc}"
            if not on:
                return ""
            deadline = self._loop.time() + SETTLE_S + 0.2
            while self._loop.time() < deadline:
                if all(sup.robot_unready(first) is None for first in robots.values()):
                    return ""
                await asyncio.sleep(0.01)
            whys = [w.why for first in robots.values() if (w := sup.robot_unready(first))]
            return "not ready: " + "; ".join(whys) if whys else ""

        return self._answered(run)

    def hold(self, command: Motion) -> None:
        """On the loop: ``command`` is this source's until it submits another, releases,
        leaves or stops proving it is alive (:meth:`alive`) for its timeout."""
        self._submit_here(command, standing=True)

    def _submit_here(self, command: Motion, *, standing: bool) -> None:
        if self._arbiter.closed:  # inputs stopped: nothing may command motion any more
            raise CommandError("the supervisor is stopping: commands are refused")
        self._arbiter.submit(self._name, command, self._arbiter.clock(), standing=standing)

    async def execute(self, text: str, *, standing: bool) -> CommandOutcome:
        """On the loop: :func:`execute` for this source's units, its motion submitted as
        its own (``standing``: held while the source proves it is alive, :meth:`alive`)."""

        def submit(command: Motion) -> None:
            self._submit_here(command, standing=standing)

        return await execute(self._sup, self._units(), text, submit)

    def holds(self) -> bool:
        """On the loop: this source still owns standing motion (it did not lapse)."""
        state = self._arbiter.sources.get(self._name)
        return state is not None and state.standing and state.fresh(self._arbiter.clock())

    def alive(self) -> None:
        """On the loop: the source proves it is alive (its standing motion holds on)."""
        self._arbiter.touch(self._name, self._arbiter.clock())

    def _units(self) -> tuple[str, ...]:
        return self._arbiter.sources[self._name].units

    def _each(self, action: Callable[..., None], *args: int) -> None:
        for unit in self._units():
            try:
                action(unit, *args)
            except CommandError as exc:
                self._sup.notice(unit, logging.WARNING, f"input {self._name} refused: {exc}")

    def _on_loop(self, fn: Callable[..., None], *args: object) -> None:
        if self._loop.is_closed():
            return
        self._loop.call_soon_threadsafe(self._unless_closed, fn, *args)

    def _unless_closed(self, fn: Callable[..., None], *args: object) -> None:
        if not self._arbiter.closed:  # inputs stopped: nothing queued may act any more
            fn(*args)

    def _submit(self, command: InputCommand | None) -> None:
        self._on_loop(self._arbiter.submit_now, self._name, command)


def _real(value: object) -> float:
    """A value :meth:`InputFeed._valid` checked, as a float (a numpy scalar too)."""
    assert isinstance(value, numbers.Real)
    return float(value)
