"""``abh3 run --headless``: run the configuration, log what matters, stop safely."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import os
import socket
import sys
from pathlib import Path

from abh3_supervisor.config.model import Config, VelocityModel
from abh3_supervisor.core.eventlog import EventLog
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import PluginError
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime import signals
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.recording import recorded, write_failures
from abh3_supervisor.runtime.stopping import final_report
from abh3_supervisor.scheduler.core import FeedbackEvent
from abh3_supervisor.service.server import ControlServer, ServiceOptions, preflight, release
from abh3_supervisor.service.view_pace import of_runtime

log = logging.getLogger("abh3")
LOG_S = 0.1  # the event lines are read from the journal this often


def status_lines(sup: Supervisor) -> list[str]:
    now = sup.clock()
    lines = []
    for bus, scheduler in sup.schedulers.items():
        for name, slot in scheduler.slots.items():
            unit, st = sup.units[name], slot.stats
            fb = unit.feedback
            travel = unit.cfg.velocity_model is VelocityModel.TRAVEL
            model = "Y/X" if travel else "A/B"
            if fb is None:
                vel = f"fbk {model} –"
            else:
                ay, bx = (fb.vel_y, fb.vel_x) if travel else (fb.vel_a, fb.vel_b)
                vel = f"fbk {model} {ay:8.1f} {bx:8.1f}"
            p50, p99 = st.rtts_ms(50, 99)
            rtt = (
                f"rtt p50 {p50:.2f} p99 {p99:.2f} ms"
                if p50 is not None and p99 is not None
                else "rtt –"
            )
            state = {True: "online", False: "OFFLINE", None: "waiting"}[slot.online]
            lines.append(
                f"{bus}/{name}: {state} {st.achieved_rate_hz(now):5.1f}/{st.requested_rate_hz:g} Hz"
                f" cmd {model} {unit.setpoint.ay + 0.0:.1f} {unit.setpoint.bx + 0.0:.1f}"
                f" {vel} {rtt}"
                f" timeouts {st.timeouts}"
            )
    return lines


async def run_headless(
    config: Config,
    *,
    duration: float | None,
    record: Path | None,
    status_interval: float,
    plugins: PluginHost | None = None,
    service: ServiceOptions | None = None,
    exit_with_stdin: bool = False,
) -> int:
    """Run until ``duration``, a stop signal, a fatal error or — with ``exit_with_stdin``
    (the TUI's child) — the end of stdin: the process that started us is gone."""
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    failed: str | None = None  # what ended the run (exit code 1)
    # a socket that cannot be served fails the run before the first frame: bound now
    bound = preflight(service) if service is not None else {}
    rt = Runtime(config, record=record, plugins=plugins, foxglove=config.foxglove)
    # the signal handlers outlive the runtime's stop and the last lines: a signal then
    # changes nothing (the CLI's own handlers, once back, would say no drive started)
    handled = contextlib.ExitStack()
    lines: _EventLines | None = None
    try:
        async with rt:
            sup = rt.supervisor

            def on_signal(signum: int) -> None:
                if stop.is_set():  # a second one: the safe word now, not the ramp down
                    sup.audit("signal", None, f"{signals.name(signum)}: SERVO off now")
                    sup.hurry()
                    return
                sup.audit("signal", None, f"{signals.name(signum)}: stop")
                stop.set()

            # only now: a signal while buses or the recording open must interrupt the open
            # (the caller's handlers do), which a loop handler cannot. Every signal that
            # would end the process (docs/signals.md).
            handled.enter_context(signals.on_loop(loop, on_signal))
            if exit_with_stdin:
                _stop_at_end_of_stdin(sup, stop)
            lines = _EventLines(sup)  # the journal's events, read at the log's pace
            servers = await _serve(rt, plugins, service, bound)
            # said once the sockets listen: a client that waits for this line can attach
            log.info(
                "running %d unit(s) on %d bus(es)%s; Ctrl-C stops the drives and exits",
                len(config.units),
                len(config.buses),
                f" for {duration:g} s" if duration is not None else "",
            )
            # what start-up built lives as long as the run: the collector's full passes
            # need not walk it (10-15 ms on the bus loop once clients come and go by the
            # thousand, whose asyncio objects leave cycles to collect)
            gc.freeze()
            reporter = asyncio.ensure_future(_report(sup, status_interval))
            logger = asyncio.ensure_future(lines.follow())
            try:
                await rt.run_until(stop, duration)
            finally:
                reporter.cancel()
                logger.cancel()
                lines.say()
                for server in servers:  # clients hear "bye" before the drives stop
                    await server.close()
            assert rt.fatal is not None
            if rt.fatal.done():
                why = rt.fatal.result()
                if isinstance(why, PluginError):
                    log.critical("stopping: %s", why)
                    failed = str(why)
                else:
                    log.critical("stopping after an internal error: %s", why)
                    failed = f"an internal error: {why}"
            else:
                for line in status_lines(sup):
                    log.info("final %s", line)
                log.info(
                    "stopping: zero and START off on every unit; SERVO and brake release off "
                    "as each drive reports standing (at most stop_ramp_s %g s)",
                    config.stop_ramp_s,
                )
    except BaseException:
        handled.close()
        raise
    finally:
        release(bound)  # what was bound and never served (the buses did not open)
    with handled:
        if lines is not None:  # the stop's own events
            lines.say()
        if record is not None:
            log.info("%s", recorded(rt, record))
        disabled = dict(plugins.why_disabled) if plugins is not None else {}
        # a run that failed (1) before a stop not confirmed (3), then 5, then 6
        return final_report(
            rt.stop_report, write_failures(rt, plugins), failed=failed, disabled=disabled
        )


def _stop_at_end_of_stdin(sup: Supervisor, stop: asyncio.Event) -> None:
    loop = asyncio.get_running_loop()
    fd = sys.stdin.fileno()

    def gone() -> None:
        sup.audit("tui", None, "the TUI that started this supervisor is gone: stop")
        stop.set()

    def readable() -> None:
        try:
            data = os.read(fd, 4096)
        except OSError:
            data = b""
        if not data:
            loop.remove_reader(fd)
            gone()

    try:
        loop.add_reader(fd, readable)
    except (OSError, ValueError):  # not a pipe the loop can watch (a file, /dev/null)
        loop.call_soon(gone)  # no process to outlive: as at its end


async def _serve(
    rt: Runtime,
    plugins: PluginHost | None,
    service: ServiceOptions | None,
    bound: dict[Path, socket.socket],
) -> list[ControlServer]:
    """The control servers on the sockets ``bound`` before the buses opened (handed over:
    each server closes its own)."""
    if service is None:
        return []
    main = bound.pop(service.path)
    pace = of_runtime(rt)  # one live view's pace for both sockets: late steps told once
    servers = [ControlServer(rt, plugins, service.path, group=service.group, sock=main, pace=pace)]
    if service.read_only_path is not None:
        sock = bound.pop(service.read_only_path)
        servers.append(
            ControlServer(rt, plugins, service.read_only_path, read_only=True, sock=sock, pace=pace)
        )
    try:
        for server in servers:
            await server.start()
    except BaseException:
        for server in servers:
            await server.close()
        raise
    return servers


class _EventLines:
    """The supervisor's events as log lines: read from its journal every ``LOG_S``, off
    the bus path (nothing is handed to the log per reply); a gap is said."""

    def __init__(self, sup: Supervisor) -> None:
        self.lines = EventLog(sup)
        self.reader = sup.journal.reader()
        self.missed = 0

    def say(self) -> None:
        for _, event, _ in self.reader.read():
            if type(event) is FeedbackEvent:  # the most of them, and never a line
                continue
            line = self.lines.line(event)
            if line is not None:
                log.log(*line)
        if self.reader.missed > self.missed:
            log.warning(
                "the log fell behind: %d event(s) not logged", self.reader.missed - self.missed
            )
            self.missed = self.reader.missed

    async def follow(self) -> None:
        with contextlib.suppress(asyncio.CancelledError):
            while True:
                await asyncio.sleep(LOG_S)
                self.say()


async def _report(sup: Supervisor, interval: float) -> None:
    if interval <= 0:
        return
    with contextlib.suppress(asyncio.CancelledError):
        while True:
            await asyncio.sleep(interval)
            for line in status_lines(sup):
                log.info("%s", line)
