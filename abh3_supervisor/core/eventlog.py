"""One line per event an operator should see: shared by the headless log and the TUI.

That includes the audit trail: every operator action (:class:`OperatorAction`: a key, a
command line, an answer to a question, an e-stop) and every change of a unit's state as
the drive reports it (online/offline; servo, start, torque, brake in its control word).
"""

from __future__ import annotations

import logging
from collections.abc import Hashable

from abh3_supervisor.core import readouts
from abh3_supervisor.core.supervisor import (
    FlagChange,
    Notice,
    OperatorAction,
    Supervisor,
    SupervisorEvent,
)
from abh3_supervisor.core.throttle import Throttle, held_note
from abh3_supervisor.protocol import flags
from abh3_supervisor.scheduler.core import HealthEvent

LOGGED_WORDS = ("error", "alarm")


def state_bits(layout: flags.Layout) -> int:
    """The control-word bits that are a unit's state for an operator (not busy/ready,
    which follow every command)."""
    return layout.servo.both | layout.start.both | layout.torque.both | layout.brake_release


def describe(event: SupervisorEvent, sup: Supervisor) -> tuple[int, str] | None:
    """The log line for an event worth an operator's attention, or None."""
    if isinstance(event, HealthEvent):
        if event.online:
            return logging.INFO, f"unit {event.unit}: online"
        ms = sup.units[event.unit].cfg.timeout_ms
        return logging.WARNING, f"unit {event.unit}: OFFLINE (no answer for {ms} ms)"
    if isinstance(event, FlagChange) and event.word in LOGGED_WORDS:
        role = sup.units[event.unit].cfg.role
        parts = []
        for sign, bits in (("+", event.set_bits), ("-", event.cleared_bits)):
            parts += [
                f"{sign}{b.name} ({readouts.fault_note(role, b) or b.en})"
                for b in flags.FAULT.set_bits(bits)
            ]
        if not parts:
            return None
        faults = ~readouts.normal_faults(role)  # a bit normal for the role is only news
        if not (event.set_bits | event.cleared_bits) & faults:
            level = logging.INFO
        elif event.word == "error" and event.set_bits & faults:
            level = logging.ERROR
        else:
            level = logging.WARNING
        return level, f"unit {event.unit}: {event.word} " + ", ".join(parts)
    if isinstance(event, FlagChange) and event.word == "control":
        layout = sup.units[event.unit].layout
        mask = state_bits(layout)
        parts = []
        for sign, bits in (("+", event.set_bits & mask), ("-", event.cleared_bits & mask)):
            parts += [f"{sign}{name}" for name in layout.control.names(bits)]
        if not parts:
            return None
        return logging.INFO, f"unit {event.unit}: drive reports " + " ".join(parts)
    if isinstance(event, Notice):
        return event.level, (f"unit {event.unit}: " if event.unit else "") + event.message
    if isinstance(event, OperatorAction):
        where = f" on {event.unit}" if event.unit else ""
        return logging.INFO, f"operator ({event.source}){where}: {event.action}"
    return None


class EventLog:
    """:func:`describe` with a memory: a word that keeps changing (a flapping input, spoofed
    status frames) gives at most ``FLAG_LINES_PER_S`` lines per unit, word and set of
    changed bits per second (so a set and its clear both show); the next line says how many
    were not shown. The current words are always on the TUI. Operator actions are never
    held back."""

    FLAG_LINES_PER_S = 4

    def __init__(self, sup: Supervisor) -> None:
        self.sup = sup
        self._throttle = Throttle(1.0, burst=self.FLAG_LINES_PER_S)

    def line(self, event: SupervisorEvent) -> tuple[int, str] | None:
        described = describe(event, self.sup)
        if described is None or not isinstance(event, FlagChange):
            return described
        key: Hashable = (event.unit, event.word)
        if event.word == "control":  # a servo change must not hide a start change after it
            changed = (event.set_bits | event.cleared_bits) & state_bits(
                self.sup.units[event.unit].layout
            )
            key = (event.unit, event.word, changed)
        held = self._throttle.allow(key, event.t)
        if held is None:
            return None
        level, text = described
        return level, text + held_note(held)
