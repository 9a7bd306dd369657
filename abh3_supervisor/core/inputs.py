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
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from abh3_supervisor.core.commands import (
    RESPONSE_INVALID,
    RESPONSE_OK,
    Command,
    CurrentCommand,
    VelocityCommand,
    parse_command,
)
from abh3_supervisor.core.text import clean
from abh3_supervisor.errors import CommandError

DEFAULT_TIMEOUT = 0.5


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
    def start(self, feed: Any) -> None:
        """Begin producing commands through ``feed`` (usually from a thread of your own):
        the host's ``InputFeed`` (plugin_host/feed.py), which the core does not know."""

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


class Commander(Protocol):
    """What the command language needs of the supervisor (core/supervisor.py's), named
    here so that this module does not import it."""

    clock: Callable[[], float]

    def apply(self, name: str, command: Command) -> None: ...
    def admit(self, name: str, command: Motion) -> str | None: ...
    def refusal(self, name: str, text: str, exc: CommandError) -> str: ...
    def notice(self, unit: str | None, level: int, message: str) -> None: ...
    def confirm(self, name: str, since: float) -> Awaitable[str]: ...


def enact(
    sup: Commander, units: tuple[str, ...], text: str, submit: Callable[[Motion], None]
) -> CommandOutcome:
    """Run the command language on ``units`` now, without waiting for the drives: the
    seed's answer per unit, ``''`` where it was taken (:func:`execute` then waits for a
    drive's reply to say so).

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
            try:
                sup.apply(unit, command)
            except CommandError as exc:
                responses[unit], reasons[unit] = sup.refusal(unit, text, exc), str(exc)
                continue
            responses[unit] = RESPONSE_OK
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
    try:
        submit(command)
    except CommandError as exc:  # the inputs stopped meanwhile
        return CommandOutcome({unit: sup.refusal(unit, text, exc) for unit in units}, {}, True)
    return CommandOutcome(dict.fromkeys(units, RESPONSE_OK), clamped, True)


async def execute(
    sup: Commander, units: tuple[str, ...], text: str, submit: Callable[[Motion], None]
) -> CommandOutcome:
    """:func:`enact`, answering as the seed's service does: each unit that took the
    command answers ``''`` once its drive replied to a frame carrying it, else the seed's
    ``Packet Error`` (``Commander.confirm``)."""
    since = sup.clock()
    outcome = enact(sup, units, text, submit)
    taken = [unit for unit, response in outcome.responses.items() if response == RESPONSE_OK]
    if not taken:
        return outcome
    answers = await asyncio.gather(*(sup.confirm(unit, since) for unit in taken))
    confirmed = dict(zip(taken, answers, strict=True))
    return replace(outcome, responses={**outcome.responses, **confirmed})


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
