"""The stop path: every commanded unit's stop frame, repeated until its drive reports the
stop, or the deadline passes; what became of each unit is said, never assumed.

A reply alone proves nothing: DP0 replies carry no sequence number, and a slow drive's
reply to a command sent before the stop can arrive after it. A stop is *confirmed* when
the drive itself reports SERVO and START off in its control word — the 2023 DP0 reply
carries it; a 2021 drive is asked for broadcast 1 with every stop frame.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING

from abh3_supervisor.protocol import frames
from abh3_supervisor.scheduler.core import FeedbackEvent, StatusEvent

if TYPE_CHECKING:
    from abh3_supervisor.core.supervisor import Supervisor, SupervisorEvent
    from abh3_supervisor.scheduler.pump import BusPump

log = logging.getLogger(__name__)
EXIT_FAILED = 1  # the run was ended by a failure (internal, a plugin's policy)
EXIT_STOP_UNCONFIRMED = 3  # the run ended, but a drive did not confirm its stop frame
EXIT_RECORDING_FAILED = 5  # the run ended, but a recording stopped early on a write error
EXIT_PLUGIN_DISABLED = 6  # the run ended, but a plugin was disabled during it
STOP_DEADLINE_S = 1.0  # stop frames are repeated until confirmed, at most this long
STOP_RETRY_S = 0.05  # a stop not confirmed within this is sent again
CONFIRMED, SENT = "confirmed", "sent, not confirmed"  # else "NOT sent: <reason>"


def reported_control(event: SupervisorEvent) -> int | None:
    """The control word a drive reports in this event, if it carries one."""
    if isinstance(event, FeedbackEvent) and isinstance(event.reply, frames.Dp0Reply2023):
        return event.reply.control
    if isinstance(event, StatusEvent) and isinstance(event.record, frames.Brd1):
        return event.record.control  # 2021 (None in 2023: its broadcast 1 has none)
    return None


async def stop_drives(
    sup: Supervisor, pumps: dict[str, BusPump], ramp_s: float = 0.0
) -> dict[str, str]:
    """Zero in the safe word to every commanded unit, until confirmed or the deadline;
    the outcome per unit (:data:`CONFIRMED`, :data:`SENT` or ``NOT sent: …``), logged.

    ``ramp_s`` > 0: first a controlled stop (stop category 1, ``Supervisor.begin_stop``):
    zero and START off at once, SERVO and brake release off on each drive as soon as it
    reports standing, at the latest after ``ramp_s`` (or at once on ``Supervisor.hurry``,
    a second stop signal)."""
    loop = asyncio.get_running_loop()
    if ramp_s > 0:
        sup.begin_stop()
        ramp_end = loop.time() + ramp_s
        while sup.gate.ramping and loop.time() < ramp_end:
            await asyncio.sleep(min(STOP_RETRY_S, ramp_end - loop.time()))
        if sup.gate.ramping:
            log.warning(
                "not every drive reported standing within stop_ramp_s %g s (%s): SERVO off now",
                ramp_s,
                ", ".join(sorted(sup.gate.ramping)),
            )
    sup.safe_state()
    deadline = loop.time() + STOP_DEADLINE_S
    units = {
        name: bus
        for bus, scheduler in sup.schedulers.items()
        for name, slot in scheduler.slots.items()
        if slot.commanding
    }
    confirmed = {name: loop.create_future() for name in units}

    def watch(event: SupervisorEvent) -> None:
        control = reported_control(event)
        unit = getattr(event, "unit", None)
        if control is None or unit not in confirmed or confirmed[unit].done():
            return
        state = sup.units[unit]
        if state.identified is not state.cfg.protocol:
            return  # bytes read in a layout the drive's replies ruled out confirm nothing
        layout = state.layout
        if not control & (layout.servo.both | layout.start.both):
            confirmed[unit].set_result(True)

    sup.subscribe(watch)
    sent: set[str] = set()
    refused: dict[str, str] = {}
    try:
        while True:
            for name, bus in units.items():
                if not confirmed[name].done():
                    _send_stop(sup, pumps.get(bus), name, sent, refused)
            waiting = [f for f in confirmed.values() if not f.done()]
            if not waiting or loop.time() >= deadline:
                break
            await asyncio.wait(waiting, timeout=min(STOP_RETRY_S, deadline - loop.time()))
    finally:
        sup.unsubscribe(watch)
    for name in units:  # a drive held for its generation: its stop cannot be read
        state = sup.units[name]
        if not confirmed[name].done() and state.identified not in (None, state.cfg.protocol):
            log.error(
                "unit %s: its replies are of a %s drive, the file says %s: its stop (the probe "
                "0x70, safe in both) cannot be confirmed from them",
                name,
                state.identified,
                state.cfg.protocol,
            )
    return _report(confirmed, sent, refused)


def _send_stop(
    sup: Supervisor, pump: BusPump | None, name: str, sent: set[str], refused: dict[str, str]
) -> None:
    if pump is None:
        refused[name] = "the bus did not open"
        return
    unit = sup.units[name]
    scheduler = sup.schedulers[unit.cfg.bus]
    if pump.send(*scheduler.send_now(name, pump.loop.time())):
        sent.add(name)
    else:
        refused[name] = pump.last_send_error or "the bus refused the frame"
        return
    if unit.layout.brd1_inputs is None:  # 2021: the control word is in broadcast 1
        pump.send(*scheduler.slots[name].poll_frames[1])


def _report(
    confirmed: dict[str, asyncio.Future[bool]], sent: set[str], refused: dict[str, str]
) -> dict[str, str]:
    report = {}
    for name, future in confirmed.items():
        if future.done():
            outcome = CONFIRMED
        else:
            future.cancel()
            outcome = SENT if name in sent else f"NOT sent: {refused.get(name, '?')}"
        report[name] = outcome
        if outcome == CONFIRMED:
            log.info("unit %s: stop frame confirmed by the drive (SERVO and START off)", name)
        else:
            log.error("unit %s: stop frame %s", name, outcome)
    return report


def final_report(
    report: dict[str, str],
    write_failures: list[str],
    *,
    failed: str | None = None,
    disabled: dict[str, str] | None = None,
) -> int:
    """The last lines of a run and the exit code they call for, said on the line that
    decides it: 1 when a failure ended the run (``failed``: why), else 3 when a drive
    did not confirm its stop, else 5 when a recording (``--record``, a plugin's output)
    stopped early on a write error, else 6 when a plugin was disabled during the run,
    else 0. ``report``: the outcome per unit from :func:`stop_drives`;
    ``write_failures``: what stopped early, by name; ``disabled``: plugin → why."""
    unconfirmed = [name for name, outcome in report.items() if outcome != CONFIRMED]
    disabled = disabled or {}
    if failed is not None:
        code = EXIT_FAILED
    elif unconfirmed:
        code = EXIT_STOP_UNCONFIRMED
    elif write_failures:
        code = EXIT_RECORDING_FAILED
    else:
        code = EXIT_PLUGIN_DISABLED if disabled else 0

    def decides(this: int) -> str:
        return f" (exit code {code})" if code == this else ""

    for name, why in sorted(disabled.items()):
        log.error("plugin %s was disabled during the run: %s", name, why)
    if write_failures:
        log.error(
            "stopped early on a write error (the disk full?): %s; each holds what was "
            "written before that%s",
            ", ".join(write_failures),
            decides(EXIT_RECORDING_FAILED),
        )
    if unconfirmed:
        log.error(
            "not every drive confirmed its stop frame: check them%s",
            decides(EXIT_STOP_UNCONFIRMED),
        )
    elif write_failures or disabled or failed is not None:
        log.info("every drive confirmed its stop frame")
    if failed is not None:
        log.error("the run was ended by a failure: %s (exit code %d)", failed, code)
    elif code == EXIT_PLUGIN_DISABLED:
        names = ", ".join(sorted(disabled))
        log.error("plugin(s) disabled during the run: %s (exit code %d)", names, code)
    return code
