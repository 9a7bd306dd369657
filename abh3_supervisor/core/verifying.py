"""The start-up check of the drives' CAN settings on a live supervisor: every unit's
check started at once, bounded by :data:`~.verify.VERIFY_DEADLINE`, and acted on per the
unit's ``verify`` — held (through the motion gate, ``Supervisor.restrict``) or released,
its waiting start-up commands run. The judgement itself is core/verify.py, which knows no
Supervisor: this module is the only one of the two that does."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterable
from dataclasses import replace
from typing import TYPE_CHECKING

from abh3_supervisor.config.model import Role, VerifyMode
from abh3_supervisor.core.verify import VERIFY_DEADLINE, DriveCheck, State, Verification
from abh3_supervisor.params.session import FormFound

if TYPE_CHECKING:
    from abh3_supervisor.core.supervisor import Supervisor

log = logging.getLogger(__name__)


# ------------------------------------------------------------ on a live supervisor


Checks = dict[str, tuple[DriveCheck, "asyncio.Future[Verification]"]]


def begin(sup: Supervisor) -> tuple[set[str], asyncio.Task[dict[str, Verification]] | None]:
    """At start (on the loop): check every commanded unit whose ``verify`` is not off, in
    the background; they are pending from now. Returns the units whose start-up commands
    must wait for it (all of them) and the task (the runtime cancels it when it stops)."""
    names = [
        u.name
        for u in sup.units.values()
        if u.cfg.role is Role.COMMAND and u.cfg.verify is not VerifyMode.OFF
    ]
    # every checked unit's start-up waits for its check: no motion before the drive says
    # it would stop by itself were this host to die (its 0x4117: Row.unsafe)
    waiting = set(names)
    for name in waiting:
        unit = sup.units[name]
        unit.verify = replace(unit.verify, startup_due=True)
    if not names:
        return waiting, None
    checks = start_checks(sup, names)
    return waiting, asyncio.ensure_future(end_checks(sup, checks, VERIFY_DEADLINE, act=True))


def announce_forms(sup: Supervisor) -> None:
    """The form each unit's probe finds, or that none is read, as a notice."""
    for scheduler in sup.schedulers.values():
        for name, channel in scheduler.params.items():

            def told(found: FormFound, name: str = name) -> None:
                level = logging.INFO if found.fmt is not None else logging.WARNING
                sup.notice(name, level, found.text())

            channel.on_form = told


async def verify_units(
    sup: Supervisor,
    names: Iterable[str],
    *,
    deadline: float = VERIFY_DEADLINE,
    act: bool = True,
) -> dict[str, Verification]:
    """Check these units' drives at once, within ``deadline``; each unit's
    :class:`Verification` is set and returned. ``act``: log it and act on it per the
    unit's ``verify`` (hold or release it, run its waiting start-up commands)."""
    return await end_checks(sup, start_checks(sup, names), deadline, act=act)


def start_checks(sup: Supervisor, names: Iterable[str]) -> Checks:
    """Each unit pending, its first request on its channel (on the running loop)."""
    loop = asyncio.get_running_loop()
    checks: Checks = {}
    for name in dict.fromkeys(names):
        unit = sup.unit(name)
        future: asyncio.Future[Verification] = loop.create_future()

        def done(v: Verification, f: asyncio.Future[Verification] = future) -> None:
            if not f.done():
                f.set_result(v)

        channel = sup.schedulers[unit.cfg.bus].params[name]
        checks[name] = (DriveCheck(sup.config, unit.cfg, channel, done), future)
        ok = unit.verify.state is State.OK
        unit.verify = replace(unit.verify, state=State.PENDING, rows=(), t=sup.clock(), prior_ok=ok)
        if unit.verify.holds():
            sup.restrict(name)  # held from now: nothing it had comes back on its own
    for name, (check, _) in checks.items():
        check.start()
        _wake(sup, name)
    return checks


async def end_checks(
    sup: Supervisor, checks: Checks, deadline: float, *, act: bool
) -> dict[str, Verification]:
    try:
        if checks:
            await asyncio.wait([f for _, f in checks.values()], timeout=deadline)
    finally:  # the deadline, or the run ending: nothing of ours stays queued
        for name, (check, _) in checks.items():
            check.abandon(sup.clock(), f"no complete answer within {deadline:g} s")
            _wake(sup, name)
    out = {}
    for name, (_, future) in checks.items():
        unit = sup.unit(name)
        out[name] = unit.verify = replace(future.result(), startup_due=unit.verify.startup_due)
        if unit.verify.holds():
            sup.restrict(name)  # fails closed: held, whatever it had is forgotten
        if act:
            _act(sup, name)
    return out


def _wake(sup: Supervisor, name: str) -> None:
    wake = sup.wakers.get(sup.unit(name).cfg.bus)
    if wake is not None:
        wake()


def _act(sup: Supervisor, name: str) -> None:
    unit = sup.unit(name)
    v = unit.verify
    refuse = v.mode is VerifyMode.REFUSE
    if v.state is State.MISMATCH:
        for row in v.mismatches:
            sup.notice(name, logging.WARNING, row.line())
        what = (
            "held at its idle word (SERVO, START, brake, torque refused) until they agree and "
            "the unit is verified again"
            if v.holds() is not None
            else "running as the file says (verify: warn)"
        )
        count = f"{len(v.mismatches)} of {len(v.rows)}"
        sup.notice(
            name,
            logging.WARNING,
            f"the drive's CAN settings differ from the file ({count}): {what}",
        )
    elif v.state is State.OK:
        form = f"; TelABH3 {v.form}" if v.form else ""
        sup.notice(
            name,
            logging.INFO,
            f"the drive's CAN settings agree with the file ({len(v.rows)} read{form})",
        )
    elif v.state is State.NOT_VERIFIED:
        if refuse:
            sup.notice(
                name,
                logging.WARNING,
                f"the drive's CAN settings are not verified: {v.reason}; held at its idle "
                "word (verify: refuse) until `abh3 verify` finds them agreeing",
            )
        else:  # its command-zero timeout unread: the fail-safe on host death unconfirmed
            sup.notice(
                name,
                logging.WARNING,
                f"the drive's CAN settings are not verified: {v.reason}; the unit runs, but "
                "nothing confirms the drive would stop were this host to die (its 0x4117 "
                "is unread): `verify: refuse` holds such a unit",
            )
    if v.startup_due and v.holds() is None:
        unit.verify = replace(v, startup_due=False)
        run_startup(sup, name)


def run_startup(sup: Supervisor, name: str) -> None:
    """The unit's ``startup:`` commands, now (validated when the file loaded); its
    motion is owned by the supervisor for the run (``Supervisor.run_startup``)."""
    for text, response in sup.run_startup(name):
        log.info("unit %s: startup %r → %r", name, text, response)


__all__ = ["announce_forms", "begin", "end_checks", "run_startup", "start_checks", "verify_units"]
