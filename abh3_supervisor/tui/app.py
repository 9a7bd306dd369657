"""The Textual app: overview, unit detail with plots, bus view, event log, driving.

It is a client of the Supervisor API and drives through the same input arbitration as
the plugins (an input source named ``tui`` with the highest priority). The runtime wraps
the app (see :func:`run_tui`), so every way out of the app stops the drives.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from rich.text import Text
from textual import work
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, VerticalScroll
from textual.css.query import NoMatches
from textual.widgets import (
    Footer,
    Header,
    Input,
    RichLog,
    Sparkline,
    Static,
    TabbedContent,
    TabPane,
)

from abh3_supervisor.config.model import Config, Role
from abh3_supervisor.eventlog import EventLog
from abh3_supervisor.inputs import InputFeed, InputSource
from abh3_supervisor.planner import plan
from abh3_supervisor.plugin_host import PluginHost
from abh3_supervisor.runtime import EXIT_STOP_UNCONFIRMED, STOP_SIGNALS, Runtime
from abh3_supervisor.runtime_thread import RuntimeThread
from abh3_supervisor.supervisor import Supervisor, SupervisorEvent
from abh3_supervisor.tui.model import (
    COLUMNS,
    BusSample,
    Sampler,
    bus_lines,
    detail_lines,
    flag_lines,
    overview_row,
)
from abh3_supervisor.tui.screens import ConfirmScreen, HelpScreen

REFRESH_S = 0.1
T = TypeVar("T")
WIDTHS = {
    "unit": 8,
    "state": 7,
    "proto": 5,
    "mode": 15,
    "servo": 7,
    "start": 7,
    "cmd": 13,
    "fbk A/B": 13,
    "fbk Y/X": 13,
    "current %": 11,
    "load %": 7,
    "supply V": 9,
    "errors": 24,
    "alarms": 24,
    "rate Hz": 9,
}
PLOTS = {
    "command": "velocity command AY [min⁻¹]",
    "feedback": "velocity feedback AY [min⁻¹]",
    "current": "current command A [%]",
    "load": "load A [%]",
}


def _cell_style(column: str, value: str) -> str:
    if (column, value) == ("state", "OFFLINE") or (column == "errors" and value != "–"):
        return "bold red"
    if column == "alarms" and value != "–":
        return "yellow"
    if column == "unit" and value.endswith("*"):
        return "reverse"
    return ""


def _styled(level: int, text: str) -> Text:
    style = "bold red" if level >= logging.ERROR else "yellow" if level >= logging.WARNING else ""
    return Text(f"{time.strftime('%H:%M:%S')} {text}", style=style)


class _PaneHandler(logging.Handler):
    """Log records into the event log pane (any thread: a deque append is atomic)."""

    def __init__(self, pending: deque[Text]) -> None:
        super().__init__(logging.INFO)
        self.pending = pending

    def emit(self, record: logging.LogRecord) -> None:
        if record.name != "abh3":  # the supervisor's own event lines arrive as events
            self.pending.append(_styled(record.levelno, record.getMessage()))


class TuiSource(InputSource):
    """The keyboard of the TUI as an input source: highest priority, 0.6 s freshness."""

    def __init__(self, units: tuple[str, ...]) -> None:
        super().__init__("tui", units, priority=100, timeout=0.6)
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None


class SupervisorApp(App[None]):
    CSS_PATH = "abh3.tcss"
    TITLE = "abh3-supervisor"
    AUTO_FOCUS = None  # keys go to the bindings; the command line takes focus only on ':'

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("ctrl+e", "estop", "E-STOP", priority=True),
        Binding("e", "estop", "E-STOP", show=False),
        Binding("E", "clear_estop", "clear e-stop"),
        Binding("up", "drive(1, 0)", "forward", show=False),
        Binding("down", "drive(-1, 0)", "back", show=False),
        Binding("left", "drive(0, 1)", "turn left", show=False),
        Binding("right", "drive(0, -1)", "turn right", show=False),
        Binding("space", "drive(0, 0)", "stop", show=False),
        Binding("plus,equals_sign", "speed(1.25)", "faster", show=False),
        Binding("minus", "speed(0.8)", "slower", show=False),
        Binding("a", "toggle_all", "all units", show=False),
        Binding("n", "select(1)", "next unit"),
        Binding("p", "select(-1)", "prev unit", show=False),
        Binding("v", "flip('SERVO')", "servo"),
        Binding("s", "flip('START')", "start"),
        Binding("b", "flip('BRAKE')", "brake", show=False),
        Binding("T", "flip('TORQUE')", "torque", show=False),
        Binding("r", "reset", "error reset", show=False),
        Binding("d", "data_select", "data select", show=False),
        Binding("f", "fault", "sim: silence", show=False),
        Binding("colon", "command", "command"),
        Binding("1", "tab('overview')", "overview", show=False),
        Binding("2", "tab('unit')", "unit", show=False),
        Binding("3", "tab('bus')", "bus", show=False),
        Binding("4", "tab('log')", "log", show=False),
        Binding("question_mark", "help", "help"),
        Binding("q", "quit_safely", "quit"),
    ]

    def __init__(
        self,
        runtime: Runtime,
        source: TuiSource,
        bridge: RuntimeThread | None = None,
        duration: float | None = None,
    ) -> None:
        super().__init__()
        self.duration = duration
        self.rt = runtime
        self.bridge = bridge  # the runtime's own thread; None: it shares this loop
        self.sup: Supervisor = runtime.supervisor
        self.source = source
        self.names = list(self.sup.units)
        self.selected = 0
        self.drive_all = False
        self.speed, self.turn = 0.2, 0.5
        self.sampler = Sampler(self.sup)
        self.bus_samples: dict[str, BusSample] = {}
        self.plans = {p.bus: p for p in plan(runtime.config)}  # static: computed once
        self.pending_log: deque[Text] = deque(maxlen=2000)
        self.overview_rows: dict[str, dict[str, str]] = {}
        self.events = EventLog(self.sup)
        self.sup.subscribe(self._on_event)
        self._log_handler = _PaneHandler(self.pending_log)

    # ------------------------------------------------------------ layout

    def compose(self) -> ComposeResult:
        yield Header()
        yield Static("EMERGENCY STOP LATCHED — E (shift+e) to clear", id="estop")
        with TabbedContent(initial="overview"):
            with TabPane("1 Overview", id="overview"):
                yield Static(id="table")
            with TabPane("2 Unit", id="unit"), VerticalScroll():
                yield Static(id="unit-head")
                with Horizontal(id="detail-flags"):
                    for word in ("inputs", "control", "io", "error", "alarm"):
                        yield Static(id=f"flags-{word}", classes="flags")
                for key, label in PLOTS.items():
                    yield Static(label, classes="plot-label")
                    yield Sparkline([], id=f"plot-{key}")
            with TabPane("3 Bus", id="bus"):
                yield Static(id="bus-view")
            with TabPane("4 Log", id="log"):
                yield RichLog(id="events", markup=False, wrap=True)
        yield Static(id="response")
        yield Input(
            placeholder="command for the selected unit, e.g. SERVO ON ON (Esc closes)", id="cmdline"
        )
        yield Footer()

    def on_mount(self) -> None:
        root = logging.getLogger()
        self._saved_handlers = root.handlers[:]
        root.handlers = [self._log_handler]  # stderr is the screen now
        self.set_interval(REFRESH_S, self.refresh_view)
        self.refresh_view()
        if self.duration is not None:  # --duration: leave (and stop the drives) in time
            self.set_timer(self.duration, self.exit)

    # ------------------------------------------------------------ refresh

    def on_unmount(self) -> None:
        logging.getLogger().handlers = self._saved_handlers

    def _on_event(self, event: SupervisorEvent) -> None:
        line = self.events.line(event)
        if line is not None:
            self.pending_log.append(_styled(*line))

    def refresh_view(self) -> None:
        with contextlib.suppress(NoMatches):  # the app is closing: widgets already gone
            self._refresh()

    def _refresh(self) -> None:
        if self.bridge is not None and not self.bridge.alive:
            self.exit(return_code=1, message="the runtime stopped: see the log")
            return
        self.sampler.sample()
        self.query_one("#estop").set_class(self.sup.estop, "latched")
        self.query_one("#table", Static).update(self._overview())
        log = self.query_one("#events", RichLog)
        while self.pending_log:
            log.write(self.pending_log.popleft())
        active = self.query_one(TabbedContent).active
        if active == "unit":
            self._refresh_unit()
        elif active == "bus":
            self.query_one("#bus-view", Static).update(
                "\n".join(bus_lines(self.rt, self.plans, self.bus_samples))
            )
        self.sub_title = (
            f"unit {self.unit}{' (all units)' if self.drive_all else ''} · "
            f"speed {self.speed:.2f} m/s, turn {self.turn:.2f} rad/s"
        )

    def _overview(self) -> Text:
        """The overview as one fixed-width text: an order of magnitude cheaper to render
        than a table widget, so the UI thread leaves the GIL to the buses."""
        text = Text(" ".join(f"{c:<{WIDTHS[c]}}" for c in COLUMNS) + "\n", style="bold")
        self.overview_rows = {}
        for i, name in enumerate(self.names):
            row = overview_row(self.sup, name)
            row["unit"] += "*" if i == self.selected else ""
            self.overview_rows[name] = row
            for column in COLUMNS:
                value = row[column][: WIDTHS[column]]
                text.append(f"{value:<{WIDTHS[column]}}", style=_cell_style(column, row[column]))
                text.append(" ")
            text.append("\n")
        return text

    def _refresh_unit(self) -> None:
        name = self.unit
        unit = self.sup.units[name]
        self.query_one("#unit-head", Static).update("\n".join(detail_lines(self.sup, name)))
        words = {"inputs": unit.inputs, **unit.words}
        for word in ("inputs", "control", "io", "error", "alarm"):
            text = Text(f"{word} 0x{words.get(word, 0):08X}\n", style="bold")
            for on, label in flag_lines(unit.layout, word, words.get(word)):
                style = (
                    (
                        "bold red"
                        if word == "error"
                        else "yellow"
                        if word == "alarm"
                        else "bold green"
                    )
                    if on
                    else "dim"
                )
                text.append(label + "\n", style=style)
            self.query_one(f"#flags-{word}", Static).update(text)
        trace = self.sampler.traces[name]
        for key, data in (
            ("command", trace.cmd),
            ("feedback", trace.fbk),
            ("current", trace.current),
            ("load", trace.load),
        ):
            self.query_one(f"#plot-{key}", Sparkline).data = list(data)

    # ------------------------------------------------------------ actions

    def call(self, fn: Callable[..., object], *args: object) -> None:
        """Change something on the runtime's side (its own thread when there is one)."""
        if self.bridge is None:
            fn(*args)
        else:
            self.bridge.call(fn, *args)

    async def run_remote(self, coro: Coroutine[Any, Any, T]) -> T:
        return await (self.bridge.run(coro) if self.bridge is not None else coro)

    @property
    def unit(self) -> str:
        return self.names[self.selected]

    def targets(self) -> tuple[str, ...]:
        commanded = [n for n in self.names if self.sup.units[n].cfg.role is Role.COMMAND]
        return tuple(commanded) if self.drive_all else (self.unit,)

    def say(self, text: str) -> None:
        self.query_one("#response", Static).update(text)

    def action_estop(self) -> None:
        self.call(self.sup.emergency_stop)
        self.say("EMERGENCY STOP: every unit zero, START off — E to clear")
        self.refresh_view()

    def action_clear_estop(self) -> None:
        if not self.sup.estop:
            return

        def answer(yes: bool | None) -> None:
            if yes:
                self.call(self.sup.clear_emergency_stop)
                self.say("e-stop cleared: give START again to move")

        self.push_screen(ConfirmScreen("Clear the emergency stop?"), answer)

    def action_drive(self, linear: int, angular: int) -> None:
        feed = self.source.feed
        if feed is None:
            return
        lin, ang = linear * self.speed, angular * self.turn
        feed.retarget(self.targets())
        feed.twist(lin, ang)
        self.say(
            f"drive {', '.join(self.targets())}: {lin:+.2f} m/s {ang:+.2f} rad/s "
            "(hold the key; release = stop)"
        )

    def action_speed(self, factor: float) -> None:
        self.speed *= factor
        self.turn *= factor

    def action_toggle_all(self) -> None:
        self.drive_all = not self.drive_all

    def action_select(self, step: int) -> None:
        self.selected = (self.selected + step) % len(self.names)

    def action_tab(self, tab: str) -> None:
        self.query_one(TabbedContent).active = tab

    def action_flip(self, what: str) -> None:
        unit = self.sup.units[self.unit]
        lay = unit.layout
        bits = {
            "SERVO": lay.servo.both,
            "START": lay.start.both,
            "BRAKE": lay.brake_release,
            "TORQUE": lay.torque.both,
        }[what]
        on = not unit.inputs & bits
        command = f"{what} {'ON ON' if on else 'OFF OFF'}"

        def answer(yes: bool | None) -> None:
            if yes:
                self.run_command(command)

        if on:  # switching something on can make a motor move: ask first
            self.push_screen(ConfirmScreen(f"{command} on unit {self.unit}?"), answer)
        else:
            self.run_command(command)

    def action_data_select(self) -> None:
        """Step both axes to the next preset table (written 7 = set #0 … 0 = #7 & STOP)."""
        unit = self.sup.units[self.unit]
        ay, _ = unit.layout.data_select(unit.inputs)
        written = (ay - 1) % 8
        command = f"SELECT {written} {written}"
        table = f"#{7 - written}" + (" & STOP" if written == 0 else "")

        def answer(yes: bool | None) -> None:
            if yes:
                self.run_command(command)

        self.push_screen(
            ConfirmScreen(f"{command} (data set {table}) on unit {self.unit}?"), answer
        )

    def action_reset(self) -> None:
        def answer(yes: bool | None) -> None:
            if yes:
                self.run_command("RESET ON ON", then="RESET OFF OFF")

        self.push_screen(
            ConfirmScreen(f"Error reset on unit {self.unit}? (the servo goes off)"), answer
        )

    def action_fault(self) -> None:
        cfg = self.sup.units[self.unit].cfg
        sim = self.rt.sims.get(cfg.bus)
        if sim is None:
            self.say("not a simulated unit")
            return
        drive = sim.drives[cfg.abh3_id]
        silent = not drive.silent
        self.call(setattr, drive, "silent", silent)
        self.say(f"simulated {self.unit} {'stops answering' if silent else 'answers again'}")

    def action_command(self) -> None:
        cmdline = self.query_one("#cmdline", Input)
        cmdline.add_class("open")
        cmdline.focus()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        text = event.value
        event.input.value = ""
        event.input.remove_class("open")
        self.set_focus(None)
        if text.strip():
            self.run_command(text)

    def key_escape(self) -> None:
        cmdline = self.query_one("#cmdline", Input)
        cmdline.remove_class("open")
        self.set_focus(None)

    @work(exclusive=False)
    async def run_command(self, text: str, then: str | None = None) -> None:
        unit = self.unit
        response = await self.run_remote(self.sup.command(unit, text))
        self.say(f"{unit} ← {text!r} → {response!r}")
        if then is not None:
            await asyncio.sleep(0.2)  # a rising edge, then back off, as the manual asks
            await self.run_remote(self.sup.command(unit, then))

    def action_help(self) -> None:
        lines = ["Keys (work from every screen)", ""]
        extra = {
            "up": "↑ forward",
            "down": "↓ back",
            "left": "← turn left",
            "right": "→ turn right",
            "space": "space stop",
        }
        for b in self.BINDINGS:
            assert isinstance(b, Binding)
            key = extra.get(b.key, b.key)
            lines.append(f"  {key:<22} {b.description}")
        lines += [
            "",
            "Driving: hold an arrow key; releasing it stops within 0.6 s.",
            "Tabs: 1 overview · 2 unit (flags, plots) · 3 bus · 4 event log.",
            "Command line (:) accepts the seed's language and shows its exact reply.",
        ]
        self.push_screen(HelpScreen(lines))

    def action_quit_safely(self) -> None:
        def answer(yes: bool | None) -> None:
            if yes:
                self.exit()

        self.push_screen(ConfirmScreen("Quit? Every unit gets zero, START and SERVO off."), answer)


def start_logged(bridge: RuntimeThread) -> tuple[Runtime, deque[Text]]:
    """Start the runtime, keeping what is logged meanwhile (plugins' start-up lines) for
    the log pane: the app, and its own log handler, exist only once the runtime runs."""
    early = _PaneHandler(deque(maxlen=200))
    logging.getLogger().addHandler(early)
    try:
        return bridge.start(), early.pending
    finally:
        logging.getLogger().removeHandler(early)


async def run_tui(
    config: Config, *, record: Path | None, plugins: PluginHost, duration: float | None = None
) -> int:
    """The TUI on this loop, the buses on a thread of their own; every exit stops drives."""
    source = TuiSource(tuple(config.units))
    plugins.add_source(source)
    bridge = RuntimeThread(config, record=record, plugins=plugins)
    runtime, early = start_logged(bridge)
    app = SupervisorApp(runtime, source, bridge, duration=duration)
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
    if app.return_code or bridge.error is not None:
        return app.return_code or 1
    return 0 if runtime.stops_confirmed else EXIT_STOP_UNCONFIRMED
