"""What a plugin sees of the supervisor: a read-only view, never the object itself.

The Supervisor is only to be touched on the event loop, and whatever sets a setpoint
there bypasses the arbitration's owner. A plugin gets a :class:`SupervisorView` instead
(its hooks' ``supervisor`` argument): the configuration, each unit's state through
read-only accessors (other hosts heard on its drive too), and the few actions that are
safe from any thread — ask for a status packet, latch the e-stop (audited as an
operator's is) and, for a plugin its user allowed to, clear it; say something to the
operator, end the run. Motion is only ever an input source's (``abh3_input_sources``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from abh3_supervisor.config.model import Config, UnitConfig
from abh3_supervisor.core.diagnostics import Health, HealthSnapshot
from abh3_supervisor.core.foreign import QUIET_S
from abh3_supervisor.core.robot import RobotConfig
from abh3_supervisor.core.state import Feedback, Setpoint, UnitState
from abh3_supervisor.core.supervisor import FlagChange, Supervisor
from abh3_supervisor.core.text import clean
from abh3_supervisor.core.verify import Verification
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags, frames

LEVELS = {logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR, logging.CRITICAL}


@dataclass(frozen=True, slots=True)
class BusCounters:
    """One bus's counters since the start (API 1.1): frames sent (commands and polls),
    frames received (replies and broadcasts), sends that failed, the interface's state
    (``ok``, ``error-warning``, ``error-passive``, ``bus-off``, …)."""

    frames_sent: int
    frames_received: int
    send_errors: int
    state: str


@dataclass(frozen=True, slots=True)
class ForeignHost:
    """Another host heard on a unit's drive (API 1.1; core/foreign.py, docs/safety.md "A
    second host on the bus"), copied when read: safe from any thread."""

    source: int  # its source address (ours too: a second copy of us uses it)
    drive: int
    commanding: bool  # it commanded the drive or opened a session on it: the robot stopped
    frames: int  # the frames of it heard in its present episode (every kind)
    lately: bool  # heard within QUIET_S (1 s) of now: still there, as /diagnostics says
    text: str  # who and what, as the notice said it: ``another host (0x02) commands …``


class UnitView:
    """One unit's state as the supervisor has it now, read-only. Each read is of the live
    state: a whole value (an int, a frozen record) or a copy, so it is safe from any
    thread; two reads may straddle an update."""

    __slots__ = ("_state",)

    def __init__(self, state: UnitState) -> None:
        self._state = state

    @property
    def name(self) -> str:
        return self._state.name

    @property
    def cfg(self) -> UnitConfig:
        """The unit's configuration (frozen)."""
        return self._state.cfg

    @property
    def layout(self) -> flags.Layout:
        """The unit's generation's flag words (name bits with it)."""
        return self._state.layout

    @property
    def inputs(self) -> int:
        """The input word commanded now."""
        return self._state.inputs

    @property
    def setpoint(self) -> Setpoint:
        """The command in force (its ``owner``: the input source it came from)."""
        return self._state.setpoint

    @property
    def feedback(self) -> Feedback | None:
        """The latest DP0 reply's feedback; None before the first."""
        return self._state.feedback

    @property
    def online(self) -> bool | None:
        """None until the unit answered or timed out once."""
        return self._state.online

    @property
    def words(self) -> Mapping[str, int]:
        """The flag words last heard (``error``, ``alarm``, ``control``, ``io``,
        ``drive_inputs``), a copy."""
        return MappingProxyType(dict(self._state.words))

    @property
    def status(self) -> Mapping[int, tuple[float, frames.Broadcast]]:
        """The latest broadcast packet of each number, with the time it arrived; a copy."""
        return MappingProxyType(dict(self._state.status))

    @property
    def verify(self) -> Verification:
        """The drive's CAN settings against the file (docs/configuration.md, verify)."""
        return self._state.verify

    @property
    def axis_limits(self) -> tuple[float, float] | None:
        """Motor A, B speed limits [min⁻¹] from the unit's robot's limits; None: none."""
        return self._state.axis_limits

    def names(self, word: str, bits: int) -> list[str]:
        """The names of ``bits`` in flag word ``word`` (any word an event names, in this
        unit's generation): ``names(change.word, change.set_bits)``."""
        return word_of(self._state.layout, word).names(bits)

    def labels(self, word: str, bits: int, lang: str = "en") -> list[str]:
        """As :meth:`names`, in words for an operator (``lang``: ``en`` or ``ja``)."""
        return word_of(self._state.layout, word).labels(bits, lang)


def word_of(layout: flags.Layout, word: str) -> flags.FlagWord:
    """The flag word ``word`` of ``layout``; ``drive_inputs`` (a 2023 drive's own report
    of its input word) is named as the input word is."""
    words = layout.words
    if word in words:
        return words[word]
    if word == "drive_inputs":
        return layout.input
    raise KeyError(f"no flag word '{word}' (words: {', '.join(words)}, drive_inputs)")


class SupervisorView:
    """The supervisor as one plugin sees it. Reads are safe from any thread; the actions
    are handed to the event loop and return at once."""

    def __init__(
        self,
        sup: Supervisor,
        loop: asyncio.AbstractEventLoop,
        plugin: str,
        end_run: Callable[[str], None] | None = None,
    ) -> None:
        self._sup, self._loop, self._plugin, self._end_run = sup, loop, plugin, end_run
        self._units = MappingProxyType({n: UnitView(u) for n, u in sup.units.items()})
        # health(): what this plugin's bus loads are measured from, one caller at a time
        self._health: Health | None = None
        self._health_lock = threading.Lock()

    @property
    def plugin(self) -> str:
        """This plugin's name (its entry point's): what audits and notices say."""
        return self._plugin

    @property
    def config(self) -> Config:
        """The whole configuration, validated (frozen)."""
        return self._sup.config

    @property
    def units(self) -> Mapping[str, UnitView]:
        """Every unit by name, in the file's order."""
        return self._units

    def robot(self, name: str) -> RobotConfig:
        """The robot called ``name``, or the robot of the unit called ``name``."""
        return self._sup.robot(name)

    @property
    def estop(self) -> bool:
        """The e-stop is latched."""
        return self._sup.estop

    @property
    def stopping(self) -> bool:
        """The way out has begun."""
        return self._sup.stopping

    def why_not_move(self, robot: str) -> str | None:
        """Why motion to ``robot`` (or the robot of the unit ``robot``) would be refused
        now — the e-stop, a hold, the robot decision naming the drive (docs/safety.md) —
        or None: an entry says it in its own answer, as the control socket does. A reason
        that resolves by itself (a drive not reporting yet) is None: that motion is taken
        and held at zero until the robot is ready."""
        try:
            for unit in self._sup.robot(robot).units:
                self._sup.refuse_motion(unit)
        except CommandError as exc:
            return str(exc)
        return None

    def owner(self, unit: str) -> str | None:
        """The input source whose command ``unit`` has now; None: nobody (zero)."""
        self._unit(unit)
        return self._sup.arbiter.owner(unit)

    def now(self) -> float:
        """The supervisor's clock: the ``t`` of every event (monotonic seconds)."""
        return self._sup.clock()

    def flag_names(self, change: FlagChange) -> tuple[list[str], list[str]]:
        """The names of the bits ``change`` set and cleared, in its unit's generation."""
        unit = self._unit(change.unit)
        return unit.names(change.word, change.set_bits), unit.names(
            change.word, change.cleared_bits
        )

    def health(self) -> HealthSnapshot:
        """Every bus's, unit's and robot's health now, as ``/diagnostics`` reports it
        (``health().statuses()``): a frozen copy of strings and numbers, no live object in
        it, safe to keep and to read from any thread. It never changes: call again for the
        next (each bus's load is measured between this view's calls, at least 0.5 s apart).

        Built on the calling thread, not the loop's (which may be waiting for this plugin's
        worker on the way out): from whole values and copies, the containers the loop
        replaces rather than changes (other hosts heard) and a copy of each round-trip
        window, so a read never fails on a change under it; two values may be one update
        of the loop apart, as two reads of a :class:`UnitView` may."""
        with self._health_lock:
            if self._health is None:
                self._health = Health(self._sup)
            return self._health.snapshot(self._sup.clock())

    def bus_counters(self) -> Mapping[str, BusCounters]:
        """Every bus's counters now, by name (API 1.1); each a whole record, read from any
        thread (two buses' may straddle an exchange)."""
        out: dict[str, BusCounters] = {}
        for bus, scheduler in self._sup.schedulers.items():
            stats = [scheduler.slots[u].stats for u in list(scheduler.slots)]
            out[bus] = BusCounters(
                frames_sent=sum(s.commands_sent + s.polls_sent for s in stats),
                frames_received=sum(s.replies + s.broadcasts for s in stats),
                send_errors=sum(s.send_errors for s in stats),
                state=str(self._sup.bus_health[bus].state),
            )
        return MappingProxyType(out)

    def foreign_hosts(self, unit: str) -> list[ForeignHost]:
        """Every other host heard on ``unit``'s drive, commanding first (API 1.1); empty
        for none (and for a monitor unit, whose drive is not ours to defend)."""
        cfg = self._unit(unit).cfg
        watch = self._sup.schedulers[cfg.bus].foreign
        now = self._sup.clock()
        # the loop replaces these dicts whole, never changes them (core/foreign.py): the
        # ones taken here are iterated safely while frames come
        records = sorted(
            (r for r in watch.hosts.values() if r.unit == unit),
            key=lambda r: (not r.commanding, r.source),
        )
        out = []
        for r in records:
            heard = list(r.heard.values())
            text = f"{r.who()} (unit {r.unit}): " + "; ".join(h.text() for h in heard)
            frames = sum(h.count for h in heard)
            out.append(
                ForeignHost(r.source, r.drive, r.commanding, frames, now - r.last <= QUIET_S, text)
            )
        return out

    # ------------------------------------------------------------ actions (any thread)

    def request_status(self, unit: str, packet: int) -> None:
        """Ask ``unit`` for broadcast ``packet`` (0–6) once; it arrives through
        ``abh3_status``. Raises :class:`CommandError` at once for an unknown unit or packet."""
        self._unit(unit)
        if isinstance(packet, bool) or not isinstance(packet, int) or not 0 <= packet <= 6:
            raise CommandError(f"broadcast packet {packet!r} is not 0-6")
        self._on_loop(self._sup.request_status, unit, packet)

    def emergency_stop(self, reason: str) -> None:
        """Latch the e-stop on every unit, from any thread, exactly as an operator's: each
        commanded unit's stop frame goes out at once; audited as this plugin's action with
        ``reason``. Honoured even once the inputs stopped. Clearing is an operator's, or
        :meth:`clear_emergency_stop`'s where the user allowed a plugin to."""
        who = f"plugin {self._plugin}"
        why = clean(str(reason))

        def latch() -> None:
            self._sup.audit(who, None, f"emergency stop: {why}")
            self._sup.emergency_stop(f"{who}: {why}")

        self._on_loop(latch)

    def clear_emergency_stop(self, reason: str) -> None:
        """Clear the e-stop exactly as an operator does (API 1.1), from any thread: START,
        SERVO and motion must be given anew; audited as this plugin's action with
        ``reason`` (say who asked). Only for a plugin whose user said so in its section
        (the ``mqtt`` plugin's ``allow_estop_clear``): a watchdog never clears what it
        latched."""
        who = f"plugin {self._plugin}"
        why = clean(str(reason))

        def clear() -> None:
            self._sup.audit(who, None, f"clear the emergency stop: {why}")
            self._sup.clear_emergency_stop(f"{who}: {why}")

        self._on_loop(clear)

    def notice(self, level: int, text: str) -> None:
        """Say ``text`` to the operator (the TUI's and headless log, other plugins'
        ``abh3_notice``) at a logging ``level``, prefixed with this plugin's name."""
        if level not in LEVELS:
            raise ValueError(f"level {level!r} is not a logging level (logging.INFO, …)")
        message = f"plugin {self._plugin}: {clean(str(text))}"
        self._on_loop(self._sup.notice, None, level, message)

    def end_run(self, reason: str) -> None:
        """End the run as a normal stop (the drives stopped, every plugin's ``abh3_stop``,
        exit 0): a script that is done. From any thread; the first request wins."""
        message = f"plugin {self._plugin} ends the run: {clean(str(reason))}"
        self._on_loop(self._sup.audit, f"plugin {self._plugin}", None, "end the run")
        self._on_loop(self._sup.notice, None, logging.WARNING, message)
        if self._end_run is not None:
            self._end_run(message)

    def _unit(self, name: str) -> UnitView:
        try:
            return self._units[name]
        except KeyError:
            names = ", ".join(self._units)
            raise CommandError(f"no unit named '{name}' (units: {names})") from None

    def _on_loop(self, fn: Callable[..., None], *args: object) -> None:
        if not self._loop.is_closed():  # after the run: nothing left to act on
            self._loop.call_soon_threadsafe(fn, *args)
