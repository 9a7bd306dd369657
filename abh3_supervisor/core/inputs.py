"""Input sources and the arbitration between them: who owns motion.

Several sources (keyboard, joystick, a network bridge, a control-socket client, …) may
target the same unit. For each unit the **winner** is, among the sources targeting it that
are *fresh* and holding a command, the one with the highest ``priority``; on a tie the most
recently heard. A command is fresh for the source's ``timeout`` after it was heard
(*streamed*: repeat it to keep moving) or, for a *standing* command (a client's ``VEL``),
for ``timeout`` after the source last proved it is alive (:meth:`InputArbiter.touch`).
When a unit's winner goes silent, releases (deadman let go), stops proving it is alive or
leaves, the unit gets **zero** at once, and every command heard before that moment no longer
counts for the unit: an older, replaced setpoint never comes back. The arbiter is sans-I/O:
it is fed submissions and the time, and applies commands through a callback.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import numbers
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from abh3_supervisor.core.commands import (
    RESPONSE_INVALID,
    RESPONSE_OK,
    CurrentCommand,
    VelocityCommand,
    parse_command,
)
from abh3_supervisor.core.kinematics import ab_to_yx
from abh3_supervisor.core.readiness import SETTLE_S
from abh3_supervisor.core.text import clean
from abh3_supervisor.errors import CommandError

if TYPE_CHECKING:
    from abh3_supervisor.core.supervisor import Supervisor

DEFAULT_TIMEOUT = 0.5
REFUSED_NOTICE_S = 1.0  # a source's invalid values are said at most once in this


@dataclass(frozen=True, slots=True)
class Twist:
    """Robot twist: linear.x [m/s], angular.z [rad/s], through each unit's geometry."""

    linear_x: float
    angular_z: float


@dataclass(frozen=True, slots=True)
class VelocityYX:
    """Travel/turn velocities [min⁻¹] at the motors."""

    y: float
    x: float


@dataclass(frozen=True, slots=True)
class Stop:
    """Zero command in whatever mode the unit is in (velocity or current)."""


# AY/BX velocity and current are the command language's own records (VEL / CUR)
InputCommand = Twist | VelocityYX | VelocityCommand | CurrentCommand | Stop
ZERO = Stop()


class InputSource(ABC):
    """Something that produces commands for some units. Subclass and register it."""

    def __init__(
        self, name: str, units: tuple[str, ...], priority: int = 0, timeout: float = DEFAULT_TIMEOUT
    ) -> None:
        self.name, self.units, self.priority, self.timeout = name, units, priority, timeout

    @abstractmethod
    def start(self, feed: InputFeed) -> None:
        """Begin producing commands through ``feed`` (usually from a thread of your own)."""

    @abstractmethod
    def stop(self) -> None:
        """Stop producing and release devices; called on every way out."""


class Feed(Protocol):
    """What a source may do: command a twist, A/B or Y/X velocities, or let go."""

    def twist(self, linear_x: float, angular_z: float) -> None: ...
    def velocity_ab(self, a: float, b: float) -> None: ...
    def velocity_yx(self, y: float, x: float) -> None: ...
    def velocity(self, ay: float, bx: float) -> None: ...
    def current(self, ay: float, bx: float) -> None: ...
    def release(self) -> None: ...


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
        """Motor-axis velocities A/B [min⁻¹], converted to each unit's model (as
        ``Supervisor.set_velocity_ab``)."""
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


Motion = VelocityCommand | CurrentCommand


@dataclass(frozen=True, slots=True)
class CommandOutcome:
    """What a command-language string did on each unit: the seed's answer per unit and,
    where a value was beyond the unit's limits or the wire's range, the clamp note."""

    responses: dict[str, str]
    clamped: dict[str, str] = field(default_factory=dict)
    motion: bool = False  # a VEL/CUR: owned by its source, not a static setpoint
    why: dict[str, str] = field(default_factory=dict)  # per unit refused: the reason

    @property
    def response(self) -> str:
        """The seed's single answer: the first unit that failed, else ``''``."""
        return next((r for r in self.responses.values() if r != RESPONSE_OK), RESPONSE_OK)


async def execute(
    sup: Supervisor, units: tuple[str, ...], text: str, submit: Callable[[Motion], None]
) -> CommandOutcome:
    """Run the command language on ``units``, answering as the seed's service does.

    Switches (``SERVO``, ``START``, …) act at once on the drive. Motion (``VEL``/``CUR``)
    is never a static setpoint: it is checked on every unit first (all or nothing, so two
    drives of one robot move together or not at all) and handed to ``submit``, which makes
    it a source's input in the arbitration — its owner's while the owner is present.
    """
    try:
        command = parse_command(text)
    except CommandError as exc:
        why = f"not understood: {exc}"
        return CommandOutcome({u: RESPONSE_INVALID for u in units}, why=dict.fromkeys(units, why))
    responses: dict[str, str] = {}
    reasons: dict[str, str] = {}  # the refusal said in the answer, not only in a notice
    if not isinstance(command, VelocityCommand | CurrentCommand):
        for unit in units:
            since = sup.clock()
            try:
                sup.apply(unit, command)
            except CommandError as exc:
                responses[unit], reasons[unit] = sup.refusal(unit, text, exc), str(exc)
                continue
            responses[unit] = await sup.confirm(unit, since)
        return CommandOutcome(responses, why=reasons)
    clamped: dict[str, str] = {}
    for unit in units:
        try:
            note = sup.admit(unit, command)
        except CommandError as exc:
            responses[unit], reasons[unit] = sup.refusal(unit, text, exc), str(exc)
            continue
        if note is not None:
            clamped[unit] = note
    if responses:  # one unit refused: none moves
        refused = ", ".join(responses)
        for unit in units:
            if unit not in responses:
                sup.notice(unit, logging.WARNING, f"{clean(text)!r} not applied: {refused} refused")
                responses[unit] = RESPONSE_INVALID
                reasons[unit] = f"not applied: {refused} refused (all or none moves)"
        return CommandOutcome({u: responses[u] for u in units}, clamped, True, reasons)
    since = sup.clock()
    try:
        submit(command)
    except CommandError as exc:  # the inputs stopped meanwhile
        return CommandOutcome({unit: sup.refusal(unit, text, exc) for unit in units}, {}, True)
    answers = await asyncio.gather(*(sup.confirm(unit, since) for unit in units))
    return CommandOutcome(dict(zip(units, answers, strict=True)), clamped, True)


@dataclass
class _SourceState:
    name: str
    units: tuple[str, ...]
    priority: int
    timeout: float
    command: InputCommand | None = None
    heard: float = -math.inf
    standing: bool = False  # the command holds while the source proves it is alive
    alive: float = -math.inf  # when the source last proved it is alive
    seq: int = 0  # the arbiter's count at its last submission (orders them on any clock)

    def expires(self) -> float:
        return (self.alive if self.standing else self.heard) + self.timeout

    def fresh(self, now: float) -> bool:
        return self.command is not None and now < self.expires()


@dataclass
class InputArbiter:
    # apply the winner's command (or ZERO) to a unit; False: the unit refused it, so it
    # is not the unit's command (a later identical one is applied anew)
    apply: Callable[[str, InputCommand], bool | None]
    clock: Callable[[], float]
    sources: dict[str, _SourceState] = field(default_factory=dict)
    # per unit: (winning source, the command applied) — None when nobody drives it
    current: dict[str, tuple[str, InputCommand] | None] = field(default_factory=dict)
    on_change: Callable[[], None] | None = None  # re-arm the deadline timer
    # a standing command lapsed: its source stopped proving it is alive (hung, stopped)
    on_lapse: Callable[[str], None] | None = None
    closed: bool = False  # inputs stopped: submissions are ignored from now on
    # per unit: what was submitted up to this count no longer counts (the unit stopped)
    held: dict[str, int] = field(default_factory=dict)
    submissions: int = 0  # submissions counted, so "after the hold" needs no clock
    # per unit: a standing command heard before this time was replaced (its owner lost the
    # unit to another source, which has since left): it must not come back
    superseded: dict[str, float] = field(default_factory=dict)
    # told each unit whose owner changed (taken over, let go, held): a client says so at once
    watchers: list[Callable[[str], None]] = field(default_factory=list)
    # unit → the units decided with it, its robot's (config.robot_of); absent: alone
    domains: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def add(self, source: InputSource) -> None:
        self.sources[source.name] = _SourceState(
            source.name, source.units, source.priority, source.timeout
        )

    def remove(self, name: str, now: float) -> None:
        """A source that goes away for good (a client disconnects): it lets go first."""
        if name in self.sources:
            self.submit(name, None, now)
            del self.sources[name]

    def submit_now(self, name: str, command: InputCommand | None) -> None:
        self.submit(name, command, self.clock())

    def submit(
        self,
        name: str,
        command: InputCommand | None,
        now: float,
        *,
        standing: bool = False,
        units: tuple[str, ...] | None = None,
    ) -> None:
        """``standing``: the command holds without repetition while the source keeps
        proving it is alive (:meth:`touch`), instead of for ``timeout`` after ``now``.
        ``units``: the source targets these from now on, in the same decision (its
        previous command never reaches them; units left behind stop if it drove them)."""
        state = self.sources[name]
        self.submissions += 1
        before = state.units
        if units is not None:
            state.units = units
        state.command, state.heard, state.seq = command, now, self.submissions
        state.standing, state.alive = standing, now
        self._decide(tuple(dict.fromkeys((*before, *state.units))), now)

    def touch(self, name: str, now: float) -> None:
        """The source proves it is alive: its standing command holds another ``timeout``."""
        state = self.sources.get(name)
        if state is not None:
            state.alive = now
            if state.standing and state.command is not None and self.on_change is not None:
                self.on_change()  # the expiry moved: re-arm the deadline

    def retarget_now(self, name: str, units: tuple[str, ...]) -> None:
        state = self.sources[name]
        before, state.units = state.units, units
        self._decide(tuple(sorted(set(before) | set(units))), self.clock())

    def owner(self, unit: str) -> str | None:
        """The source whose command the unit has now, or None (zero)."""
        current = self.current.get(unit)
        return None if current is None else current[0]

    def hold(self, unit: str) -> None:
        """The unit stopped (a gap, offline, the e-stop, a hold, a parameter write): only a
        command submitted after this call may move it again; a value that was fresh before
        is never resumed. The whole robot of the unit stops with it; the caller zeroes the
        unit (the Supervisor zeroes the rest of its robot)."""
        for member in self.domain(unit):
            had = self.current.get(member)
            self.held[member] = self.submissions
            self.current[member] = None
            if member != unit and had is not None:
                self.apply(member, ZERO)
            self._changed(member)

    def _changed(self, unit: str) -> None:
        for watch in self.watchers:
            watch(unit)

    def poll(self, now: float) -> None:
        """Expire silent sources (call at :meth:`next_deadline`)."""
        units = {u for s in self.sources.values() if s.command is not None for u in s.units}
        self._decide(tuple(sorted(units)), now)

    def next_deadline(self) -> float:
        return min(
            (s.expires() for s in self.sources.values() if s.command is not None),
            default=math.inf,
        )

    def domain(self, unit: str) -> tuple[str, ...]:
        """The units decided together with ``unit``: its robot's (one unit if alone)."""
        return self.domains.get(unit, (unit,))

    def _decide(self, units: tuple[str, ...], now: float) -> None:
        done: set[str] = set()
        for unit in units:
            if unit not in done:
                domain = self.domain(unit)
                done.update(domain)
                self._decide_domain(domain, now)
        self._expire(now)

    def _decide_domain(self, domain: tuple[str, ...], now: float, *, again: bool = False) -> None:
        """One winner for the whole robot: its twist drives every unit of it; any other
        command drives the units its source targets and the rest of the robot gets zero,
        so a robot never has two owners. All or nothing: a unit that refuses stops the
        robot. ``again``: apply the winner's commands anew (a ramp's next step)."""
        # plain loops, no generators: a setpoint may come every exchange
        since, replaced, previous = 0, -math.inf, None
        for u in domain:
            since = max(since, self.held.get(u, 0))
            replaced = max(replaced, self.superseded.get(u, -math.inf))
            if previous is None and (c := self.current.get(u)) is not None:
                previous = c[0]
        best: _SourceState | None = None  # the first of the highest (priority, heard)
        for s in self.sources.values():
            if (
                s.seq > since
                and s.fresh(now)
                and not (s.standing and s.heard < replaced)
                and any(u in s.units for u in domain)
                and (best is None or (s.priority, s.heard) > (best.priority, best.heard))
            ):
                best = s
        if previous is not None and (best is None or best.name != previous):
            owner = self.sources.get(previous)
            if owner is None or not owner.fresh(now):
                # the owner of the active setpoint left (silence, release, gone): a
                # standing command given before now was replaced and never comes back
                for unit in domain:
                    self.superseded[unit] = now
                if best is not None and best.standing and best.heard < now:
                    best = None
        wanted = {u: _share(best, u) for u in domain}
        if not again and all(wanted[u] == self.current.get(u) for u in domain):
            return
        before = {u: self.owner(u) for u in domain}
        refused = False
        for unit in domain:
            chosen, had = wanted[unit], self.current.get(unit)
            if chosen == had and not again:
                continue
            self.current[unit] = chosen
            if chosen is not None:
                if self.apply(unit, chosen[1]) is False:  # refused: not the unit's command
                    self.current[unit] = None
                    refused = True
                    break
            elif had is not None:
                self.apply(unit, ZERO)  # silence or release means zero (velocity or current)
        if refused:  # the robot moves whole or not at all
            for unit in domain:
                if self.current.get(unit) is not None:
                    self.current[unit] = None
                    self.apply(unit, ZERO)
        for unit in domain:
            if self.owner(unit) != before[unit]:
                self._changed(unit)  # once the unit has it (a refusal leaves it with nobody)

    def again(self, unit: str) -> None:
        """Apply ``unit``'s robot's winning commands anew (a twist's ramp steps on)."""
        self._decide_domain(self.domain(unit), self.clock(), again=True)

    def _expire(self, now: float) -> None:
        for state in self.sources.values():
            if state.command is not None and not state.fresh(now):
                state.command = None  # expired: forget it, so a late deadline is not kept
                if state.standing and self.on_lapse is not None:
                    self.on_lapse(state.name)
        if self.on_change is not None:
            self.on_change()


def _share(best: _SourceState | None, unit: str) -> tuple[str, InputCommand] | None:
    """What the robot's winner gives ``unit``: its twist (to the whole robot), its other
    commands to the units it targets; None (zero) to the rest."""
    if best is None or best.command is None:
        return None
    if isinstance(best.command, Twist) or unit in best.units:
        return best.name, best.command
    return None
