"""Running the TUI: the buses on a thread of their own, the app on this one, and every
way out stopping the drives."""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from pathlib import Path

from rich.text import Text

from abh3_supervisor.clients.tui.app import PaneHandler, SupervisorApp, TuiSource
from abh3_supervisor.config.model import Config
from abh3_supervisor.plugin_host import terminal
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.plugin_host.terminal import KeyInput
from abh3_supervisor.runtime.bus_runtime import EXIT_STOP_UNCONFIRMED, STOP_SIGNALS, Runtime
from abh3_supervisor.runtime.recording import recorded
from abh3_supervisor.runtime.thread import RuntimeThread

log = logging.getLogger("abh3")


def start_logged(bridge: RuntimeThread) -> tuple[Runtime, deque[Text]]:
    """Start the runtime, keeping what is logged meanwhile (plugins' start-up lines) for
    the log pane: the app, and its own log handler, exist only once the runtime runs."""
    early = PaneHandler(deque(maxlen=200))
    logging.getLogger().addHandler(early)
    try:
        return bridge.start(), early.pending
    finally:
        logging.getLogger().removeHandler(early)


def key_inputs(plugins: PluginHost) -> dict[str, KeyInput]:
    """Input sources that would read the terminal: the app hands them keys instead."""
    return {s.name: s for s in plugins.sources if isinstance(s, KeyInput)}


async def run_tui(
    config: Config, *, record: Path | None, plugins: PluginHost, duration: float | None = None
) -> int:
    """The TUI on this loop, the buses on a thread of their own; every exit stops drives."""
    source = TuiSource(tuple(config.units))
    plugins.add_source(source)
    bridge = RuntimeThread(config, record=record, plugins=plugins)
    terminal.claim("the TUI")  # before any input source starts: one reader of the keys
    try:
        runtime, early = start_logged(bridge)
        app = SupervisorApp(
            runtime, source, bridge, duration=duration, key_inputs=key_inputs(plugins)
        )
        app.pending_log.extendleft(reversed(early))
        loop = asyncio.get_running_loop()
        for sig in STOP_SIGNALS:
            loop.add_signal_handler(sig, app.exit)
        try:
            await app.run_async()
        finally:
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
            bridge.stop()  # leaves the runtime: the stop frames, repeated until confirmed
    finally:
        terminal.release()
    if record is not None:
        log.info("%s", recorded(runtime, record))
    if app.return_code or bridge.error is not None:
        return app.return_code or 1
    return 0 if runtime.stops_confirmed else EXIT_STOP_UNCONFIRMED
