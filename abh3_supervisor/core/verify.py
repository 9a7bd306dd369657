"""The drive and the file agree, or you are told: the start-up check of a drive's CAN
settings (docs/hardware.md §3).

Per unit the drive's parameters that must match the file are read over its parameter
channel — read-only, one after the other, beside the DP0 exchanges that keep running —
and compared (:data:`CHECKS`): CAN function (0x4100 must be 2), bitrate (0x4101, the bus's
``bitrate``; a value below 10000 is read as kbit/s, any other as bit/s: the public sources
hold both), own address (0x4102, ``abh3_id``), host address (0x4103, ``host_id``, or −1 =
any host), DP0 reply mode (0x4105 must be 0 or periodic), broadcast group (0x4107,
``brd_group``) and command-zero timeout (0x4117, ``drive_timeout_ms``). ``protocol`` and
``velocity_model`` have no parameter the public sources place: the drive's replies tell
them (``abh3 scan``, the supervisor's model notice).

:class:`DriveCheck` is the sans-I/O part (fed by the channel's callbacks, so it runs on
the fake clock too); :func:`verify_units` runs checks on a live supervisor, all units at
once, bounded by :data:`VERIFY_DEADLINE`, and acts on the outcome per the unit's
``verify`` (warn, refuse, off). Its outcome is the unit's :class:`Verification`
(``UnitState.verify``), which the snapshot, ``abh3 status`` and the diagnostics show. A
unit with ``verify: refuse`` is *held* — the motion gate (core/gate.py) sends its safe
word, SERVO, START, brake release and motion are refused, its start-up commands wait —
until a verification finds its drive agreeing: it fails closed, so a drive that differs,
does not answer, or has not been checked yet keeps it held (:meth:`Verification.holds`)
until ``abh3 verify`` (``verifying.verify_units``) succeeds. A unit already verified
runs on while it is checked again; if the new check does not agree it is held. With
``verify: warn`` a drive that differs or does not answer is reported and runs — except a
drive whose command-zero timeout reads 0 (off): nothing would stop its motors were this
host to die, so it is held in either mode. The start-up commands of both modes wait for
the check (at most ``VERIFY_DEADLINE``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from abh3_supervisor.config.model import Config, Role, UnitConfig, VerifyMode
from abh3_supervisor.params import table
from abh3_supervisor.params.session import ParamChannel, Result
from abh3_supervisor.params.telabh3 import Command, Request, form_name, pin

log = logging.getLogger(__name__)
VERIFY_DEADLINE = 2.0  # s: the whole check of a bus (its units' channels run side by side)
COMMAND_ZERO = 0x4117  # the drive's own stop when its host falls silent
KBITS_BELOW = 10_000  # 0x4101 below this is kbit/s (the table's 500), else bit/s (250000)


class State(StrEnum):
    PENDING = "pending"  # being read
    OK = "ok"  # every setting read and as the file says
    MISMATCH = "mismatch"  # at least one setting differs
    NOT_VERIFIED = "not verified"  # the drive did not answer (all of it)
    OFF = "off"  # not checked: verify: off, or a monitor (at start only commanded units)


@dataclass(frozen=True, slots=True)
class Row:
    """One setting: the drive's value as read (None: not read) against the file's."""

    address: int
    drive: str | None
    yaml: str  # "drive_timeout_ms: 500 (robot.yaml:31)", or "must be 2 (control over CAN)"
    ok: bool
    why: str | None = None  # not read: why
    # the drive would run on were its host to die (its command-zero timeout off): held
    # whatever ``verify`` says, but off (then nothing is read)
    unsafe: bool = False

    @property
    def name(self) -> str:
        return table.label(self.address)

    @property
    def verdict(self) -> str:
        if self.drive is None:
            return f"not read: {self.why}"
        return "ok" if self.ok else "MISMATCH"

    @property
    def mismatch(self) -> bool:
        return self.drive is not None and not self.ok

    def line(self) -> str:
        """``drive 0x4117 CAN_COMMAND_ZERO_TIMEOUT = 750 ms, YAML drive_timeout_ms: 500``."""
        yaml = self.yaml if self.yaml.startswith("must") else f"YAML {self.yaml}"
        return f"drive 0x{self.address:04X} {self.name} = {self.drive}, {yaml}"

    def text(self) -> str:
        if self.drive is None:
            return f"0x{self.address:04X} {self.name}: {self.verdict}"
        return self.line()

    def to_json(self) -> dict[str, Any]:
        return {
            "address": self.address,
            "name": self.name,
            "drive": self.drive,
            "yaml": self.yaml,
            "verdict": self.verdict,
            "text": self.text(),
        }


@dataclass(frozen=True, slots=True)
class Verification:
    """A unit's last check (see the module docstring); ``startup_due``: its start-up
    commands wait for a verification that does not hold the unit."""

    state: State
    mode: VerifyMode
    rows: tuple[Row, ...] = ()
    reason: str | None = None  # not verified: why; off: why not checked
    form: str | None = None  # the TelABH3 form the drive was read in
    t: float | None = None  # when it started (pending) or ended
    startup_due: bool = False
    prior_ok: bool = False  # pending again after agreeing: it runs on until the answer

    @classmethod
    def initial(cls, cfg: UnitConfig) -> Verification:
        if cfg.verify is VerifyMode.OFF:
            return cls(State.OFF, cfg.verify, reason="verify: off")
        if cfg.role is not Role.COMMAND:
            return cls(State.OFF, cfg.verify, reason="a monitor: only commanded units")
        return cls(State.NOT_VERIFIED, cfg.verify)  # no reason: not tried (yet)

    @property
    def mismatches(self) -> tuple[Row, ...]:
        return tuple(r for r in self.rows if r.mismatch)

    def holds(self) -> str | None:
        """Why the unit is held at its idle word now (``verify: refuse``, or a drive that
        would run on without its host: :attr:`Row.unsafe`), or None."""
        unsafe = next((r for r in self.rows if r.unsafe), None)
        if unsafe is not None and self.mode is VerifyMode.WARN:
            return (
                f"its drive's command-zero timeout is off ({unsafe.line()}): were this host "
                "to die its motors would run on, so it is held whatever `verify` says; set "
                "0x4117 (`abh3 param set UNIT 0x4117 MS`), then `abh3 verify` it"
            )
        if self.mode is not VerifyMode.REFUSE:
            return None
        if self.state is State.PENDING and not self.prior_ok:
            return "its drive's CAN settings are being compared with the file (verify: refuse)"
        if self.state is State.NOT_VERIFIED:
            if self.reason is None:
                return "its drive's CAN settings are not verified yet (verify: refuse)"
            return (
                f"its drive's CAN settings could not be verified (verify: refuse): "
                f"{self.reason}; `abh3 verify` it again once the drive answers"
            )
        if self.state is State.MISMATCH:
            first = self.mismatches[0].line()
            more = f" and {len(self.mismatches) - 1} more" if len(self.mismatches) > 1 else ""
            return (
                f"its drive's CAN settings differ from the file (verify: refuse): {first}{more};"
                " fix the drive or the file, then verify it again"
            )
        return None

    def summary(self) -> str | None:
        """A few words for a status line; None when nothing was tried."""
        if self.state is State.MISMATCH:
            return "verify MISMATCH: " + "; ".join(r.line() for r in self.mismatches)
        if self.state is State.NOT_VERIFIED:
            return None if self.reason is None else f"verify: not verified ({self.reason})"
        if self.state is State.OFF:
            return None
        return f"verify {self.state}"

    def to_json(self) -> dict[str, Any]:
        return {
            "state": self.state.value,
            "mode": self.mode.value,
            "mismatches": [r.to_json() for r in self.mismatches],
            "rows": [r.to_json() for r in self.rows],
            "reason": self.reason,
            "form": self.form,
            "t": self.t,
            "held": self.holds(),
        }


# ------------------------------------------------------------ the settings and the file


@dataclass(frozen=True, slots=True)
class Check:
    address: int
    key: str | None  # the unit's key in the file; None: the bus's bitrate, or a fixed rule
    judge: Callable[[float, UnitConfig, int], tuple[bool, str, str]]  # → ok, drive, file


def _number(v: float) -> str:
    return table.display(v)


def _function(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    return v == 2, _number(v), "must be 2 (control over CAN)"


def _bitrate(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    kbit = v < KBITS_BELOW
    bits = v * 1000 if kbit else v
    shown = f"{_number(v)} ({'kbit/s' if kbit else 'bit/s'})"
    return bits == bitrate, shown, f"bitrate: {bitrate}"


def _address(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    return v == u.abh3_id, _number(v), f"abh3_id: {u.abh3_id}"


def _host(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    shown = "-1 (any host)" if v == -1 else _number(v)
    return v in (-1, u.host_id), shown, f"host_id: {u.host_id}"


def _reply_mode(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    shown = {-1.0: "-1 (no replies)", 0.0: "0 (on receipt)"}.get(v, f"{_number(v)} ms")
    rule = "must be 0 (on receipt) or 1-1000 ms (periodic)"
    return v == 0 or (1 <= v <= 1000 and v == int(v)), shown, rule


def _group(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    return v == u.brd_group, _number(v), f"brd_group: {u.brd_group}"


def _zero_timeout(v: float, u: UnitConfig, bitrate: int) -> tuple[bool, str, str]:
    shown = "0 (off)" if v == 0 else f"{_number(v)} ms"
    return v == u.drive_timeout_ms, shown, f"drive_timeout_ms: {u.drive_timeout_ms}"


CHECKS = (
    Check(0x4100, None, _function),
    Check(0x4101, None, _bitrate),
    Check(0x4102, "abh3_id", _address),
    Check(0x4103, "host_id", _host),
    Check(0x4105, None, _reply_mode),
    Check(0x4107, "brd_group", _group),
    Check(COMMAND_ZERO, "drive_timeout_ms", _zero_timeout),
)


def where(config: Config, unit: UnitConfig, check: Check) -> str:
    """`` (robot.yaml:31)`` where the file sets it, `` (the default)`` where it does not."""
    src = config.source
    if check.address == 0x4101:
        path: tuple[str | int, ...] = ("buses", unit.bus, "bitrate")
    elif check.key is not None:
        path = ("units", list(config.units).index(unit.name), check.key)
    else:
        return ""
    if src is None or path not in src.lines:
        return " (the default)"
    return f" ({config.file}:{src.lines[path]})"


def compare(config: Config, unit: UnitConfig, check: Check, word: int) -> Row:
    value = table.to_value(word, table.kind_of(check.address))
    if not math.isfinite(value):
        return Row(check.address, f"word {word:08X} (no number)", "must be a number", False)
    ok, drive, yaml = check.judge(value, unit, config.buses[unit.bus].bitrate)
    if check.address == 0x4101:
        yaml = f"buses.{unit.bus}.{yaml}"
    unsafe = check.address == COMMAND_ZERO and value == 0
    return Row(check.address, drive, yaml + where(config, unit, check), ok, unsafe=unsafe)


def form_of(channel: ParamChannel) -> str | None:
    """The TelABH3 form the unit's channel uses, and how it came to."""
    if channel.fmt is None:
        return None
    if channel.pinned:
        return f"{form_name(channel.fmt)}, set by {pin(channel.fmt)}"
    return f"{form_name(channel.fmt)}, found; pin it with `{pin(channel.fmt)}`"


class DriveCheck:
    """Reads one unit's settings through its channel, one request after the other, and
    ends in a :class:`Verification` handed to ``on_done`` (once). A transport failure
    ends it at once ("not verified"); a NAK leaves that setting not read."""

    def __init__(
        self,
        config: Config,
        unit: UnitConfig,
        channel: ParamChannel,
        on_done: Callable[[Verification], None],
    ) -> None:
        self.config, self.unit, self.channel, self.on_done = config, unit, channel, on_done
        self.rows: list[Row] = []
        self.finished = False

    def start(self) -> None:
        self._next()

    def _next(self) -> None:
        check = CHECKS[len(self.rows)]
        self.channel.submit(Request(Command.PARAM, check.address), self._answered)

    def _answered(self, result: Result) -> None:
        if self.finished:
            return
        check = CHECKS[len(self.rows)]
        if result.error is not None:
            self._finish(result.t, result.error)
            return
        assert result.reply is not None
        if not result.reply.ok:
            self.rows.append(Row(check.address, None, "", False, "the drive refused it (NAK)"))
        else:
            try:
                self.rows.append(compare(self.config, self.unit, check, result.reply.word))
            except ValueError as exc:  # a reply that is no word
                self.rows.append(Row(check.address, None, "", False, str(exc)))
        if len(self.rows) == len(CHECKS):
            self._finish(result.t, None)
        else:
            self._next()

    def abandon(self, t: float, why: str) -> None:
        """Stop waiting (the deadline, the run ending): what was not read is not verified."""
        if not self.finished:
            self.channel.withdraw(self._answered, why)
            self._finish(t, why)

    def _finish(self, t: float, why: str | None) -> None:
        self.finished = True
        rows = list(self.rows)
        for check in CHECKS[len(rows) :]:
            rows.append(Row(check.address, None, "", False, why or "not asked"))
        mismatch = any(r.mismatch for r in rows)
        unread = [r for r in rows if r.drive is None]
        if mismatch:
            state, reason = State.MISMATCH, None
        elif not unread:
            state, reason = State.OK, None
        elif why is not None:
            state, reason = State.NOT_VERIFIED, why
        else:
            names = ", ".join(f"0x{r.address:04X} ({r.why})" for r in unread)
            state, reason = State.NOT_VERIFIED, f"not read: {names}"
        when = t if math.isfinite(t) else None  # a cancelled request has no time
        self.on_done(
            Verification(state, self.unit.verify, tuple(rows), reason, form_of(self.channel), when)
        )


__all__ = ["CHECKS", "DriveCheck", "Row", "State", "Verification", "compare", "form_of"]
