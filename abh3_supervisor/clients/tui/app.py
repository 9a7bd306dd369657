"""The Textual app: overview, unit detail, bus view, event log, plots, driving.

It is a client of the Supervisor API and drives through the same input arbitration as
the plugins (an input source named ``tui`` with the highest priority). The runtime wraps
the app (see :mod:`abh3_supervisor.clients.tui.run`), so every way out of the app stops the
drives. The app owns the terminal: input plugins that read keys get theirs from it
(:mod:`abh3_supervisor.plugin_host.terminal`), after its own — e-stop, tabs and quit always win.
Every operator action goes to the supervisor's audit trail, and so to the event log.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable, Coroutine, Mapping
from typing import Any, ClassVar, TypeVar

from rich.text import Text
from textual import events, work
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Grid, VerticalScroll
from textual.css.query import NoMatches
from textual.keys import _character_to_key, format_key, key_to_character
from textual.widgets import Footer, Header, Input, RichLog, Static, TabbedContent, TabPane

from abh3_supervisor.clients.tui import operator, overview, plots
from abh3_supervisor.clients.tui.help import help_lines
from abh3_supervisor.clients.tui.model import (
    SERIES,
    BusSample,
    Sampler,
    bus_fields,
    detail_fields,
    fault_lines,
    flag_lines,
    pack,
    reported,
)
from abh3_supervisor.clients.tui.screens import ConfirmScreen, HelpScreen
from abh3_supervisor.config.model import Role
from abh3_supervisor.core.commands import RESPONSE_OK
from abh3_supervisor.core.eventlog import EventLog
from abh3_supervisor.core.inputs import InputFeed, InputSource
from abh3_supervisor.core.planner import plan
from abh3_supervisor.core.supervisor import Supervisor, SupervisorEvent
from abh3_supervisor.plugin_host.terminal import KeyInput
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.thread import RuntimeThread
from abh3_supervisor.scheduler.core import HealthEvent

REFRESH_S = 0.1
T = TypeVar("T")
TABS = {"1": "overview", "2": "unit", "3": "bus", "4": "log", "5": "plots"}
FLAG_BOXES = ("inputs", "control", "io")
SET_STYLE = {"inputs": "bold cyan", "control": "bold green", "io": "bold green"}
WIDE_FLAGS = 130  # below this the flag boxes go two by two: no name is ever cut
DRIVE = "(hold; release = stop within 0.6 s)"


def styled(level: int, text: str) -> Text:
    style = "bold red" if level >= logging.ERROR else "yellow" if level >= logging.WARNING else ""
    return Text(f"{time.strftime('%H:%M:%S')} {text}", style=style)


class PaneHandler(logging.Handler):
    """Log records into the event log pane (any thread: a deque append is atomic)."""

    def __init__(self, pending: deque[Text]) -> None:
        super().__init__(logging.INFO)
        self.pending = pending

    def emit(self, record: logging.LogRecord) -> None:
        if record.name != "abh3":  # the supervisor's own event lines arrive as events
            self.pending.append(styled(record.levelno, record.getMessage()))


class TuiSource(InputSource):
    """The keyboard of the TUI as an input source: highest priority, 0.6 s freshness."""

    def __init__(self, units: tuple[str, ...]) -> None:
        super().__init__("tui", units, priority=100, timeout=0.6)
        self.feed: InputFeed | None = None

    def start(self, feed: InputFeed) -> None:
        self.feed = feed

    def stop(self) -> None:
        self.feed = None


def _b(key: str, action: str, short: str, long: str = "", show: bool = False) -> Binding:
    return Binding(key, action, short, show=show, tooltip=long or short)


class SupervisorApp(App[None]):
    CSS_PATH = "abh3.tcss"
    TITLE = "abh3-supervisor"
    AUTO_FOCUS = None  # keys go to the bindings; the command line takes focus only on ':'

    ESTOP = "EMERGENCY STOP: every unit zero, START off, latched"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("ctrl+e", "estop", "E-STOP", priority=True, tooltip=ESTOP),
        _b("e", "estop", "E-STOP", ESTOP),
        _b("E", "clear_estop", "clear e-stop", "clear the e-stop (asks; START again to move)"),
        _b("up", "drive(1, 0)", "forward", f"forward {DRIVE}"),
        _b("down", "drive(-1, 0)", "back", f"back {DRIVE}"),
        _b("left", "drive(0, 1)", "turn left", f"turn left {DRIVE}"),
        _b("right", "drive(0, -1)", "turn right", f"turn right {DRIVE}"),
        _b("space", "drive(0, 0)", "stop", "stop driving now"),
        _b("plus,equals_sign", "speed(1.25)", "faster", "arrow speeds ×1.25, up to the limit"),
        _b("minus", "speed(0.8)", "slower", "arrow speeds ×0.8"),
        _b("a", "toggle_all", "all units", "the arrows drive every commanded unit / one"),
        _b("n", "select(1)", "next unit", show=True),
        _b("p", "select(-1)", "prev unit", "select the previous unit"),
        _b("v", "flip('SERVO')", "servo", "servo as the drive reports it, flipped (on asks)", True),
        _b("s", "flip('START')", "start", "start as the drive reports it, flipped (on asks)", True),
        _b("b", "flip('BRAKE')", "brake", "brake release, flipped (release asks)"),
        _b("T", "flip('TORQUE')", "torque", "torque (current) mode, flipped (on asks)"),
        _b("r", "reset", "error reset", "error reset, servo off after it (asks)"),
        _b("d", "data_select", "data select", "next data-select preset table (asks)"),
        _b("f", "fault", "sim: silence", "simulated units: stop answering / answer again"),
        _b("colon", "command", "command", "command line in the seed's language", True),
        _b("P", "params", "parameters", "the selected unit's parameters: read, edit, diff"),
        _b("1", "tab('overview')", "overview", "tab 1: every unit"),
        _b("2", "tab('unit')", "unit", "tab 2: the selected unit, every flag bit"),
        _b("3", "tab('bus')", "bus", "tab 3: frames/s, load, errors per bus"),
        _b("4", "tab('log')", "log", "tab 4: the event log and audit trail"),
        _b("5", "tab('plots')", "plots", "tab 5: plots of the selected unit (30 s)"),
        _b("pageup", "scroll(-1)", "page up", "scroll the tab up"),
        _b("pagedown", "scroll(1)", "page down", "scroll the tab down"),
        _b("question_mark", "help", "help", "this help", True),
        _b("q", "quit_safely", "quit", "quit (asks; stops the drives)", True),
    ]

    def __init__(
        self,
        runtime: Runtime,
        source: TuiSource,
        bridge: RuntimeThread | None = None,
        duration: float | None = None,
        key_inputs: Mapping[str, KeyInput] | None = None,
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
        self.events = EventLog(self.sup)
        self._log_handler = PaneHandler(self.pending_log)
        self._last_audit: tuple[str, float] = ("", 0.0)
        self.key_inputs: list[tuple[KeyInput, dict[str, str]]] = []
        self.plugin_keys: dict[str, dict[str, str]] = {}
        taken = {
            self._char(k) for b in self.BINDINGS if isinstance(b, Binding) for k in b.key.split(",")
        }
        for i, (name, key_input) in enumerate((key_inputs or {}).items()):
            keys = key_input.key_map(taken)
            self.key_inputs.append((key_input, keys))
            self.plugin_keys[name] = keys
            for ch in keys:
                self.bind(_character_to_key(ch), f"plugin_key({i}, {ord(ch)})", show=False)
        self.call(self._watch_events)

    @staticmethod
    def _char(key: str) -> str:
        return key_to_character(key) or format_key(key)

    def _watch_events(self) -> None:
        """On the runtime's loop, so no event slips between: subscribe, and log the units
        that came online before the app existed."""
        self.sup.subscribe(self._on_event)
        for name, unit in self.sup.units.items():
            if unit.online:
                self._on_event(HealthEvent(name, self.sup.clock(), True))

    # ------------------------------------------------------------ layout

    def compose(self) -> ComposeResult:
        yield Header()
        yield Static("EMERGENCY STOP LATCHED — E (shift+e) to clear", id="estop")
        with TabbedContent(initial="overview"):
            with TabPane("1 Overview", id="overview"), VerticalScroll(id="overview-scroll"):
                yield Static(id="table")
            with TabPane("2 Unit", id="unit"), VerticalScroll(id="unit-scroll"):
                yield Static(id="unit-head")
                with Grid(id="detail-flags"):
                    for word in (*FLAG_BOXES, "faults"):
                        yield Static(id=f"flags-{word}", classes="flags")
            with TabPane("3 Bus", id="bus"), VerticalScroll(id="bus-scroll"):
                yield Static(id="bus-view")
            with TabPane("4 Log", id="log"):
                yield RichLog(id="log-scroll", markup=False, wrap=True)
            with TabPane("5 Plots", id="plots"), VerticalScroll(id="plots-scroll"):
                yield Static(id="plots-view")
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

    def on_unmount(self) -> None:
        logging.getLogger().handlers = self._saved_handlers

    def on_resize(self, event: events.Resize) -> None:
        columns = 4 if event.size.width >= WIDE_FLAGS else 2
        with contextlib.suppress(NoMatches):
            self.query_one("#detail-flags", Grid).styles.grid_size_columns = columns

    # ------------------------------------------------------------ refresh

    def _on_event(self, event: SupervisorEvent) -> None:
        line = self.events.line(event)
        if line is not None:
            self.pending_log.append(styled(*line))

    def refresh_view(self) -> None:
        with contextlib.suppress(NoMatches):  # the app is closing: widgets already gone
            self._refresh()

    def _width(self, widget_id: str) -> int:
        width = self.query_one(widget_id).content_size.width
        return width if width > 0 else self.size.width - 2

    def _refresh(self) -> None:
        if self.bridge is not None and not self.bridge.alive:
            self.exit(return_code=1, message="the runtime stopped: see the log")
            return
        self.sampler.sample()
        self.query_one("#estop").set_class(self.sup.estop, "latched")
        self.query_one("#table", Static).update(
            overview.render(self.sup, self.names, self.selected, self._width("#table"))
        )
        log = self.query_one("#log-scroll", RichLog)
        while self.pending_log:
            log.write(self.pending_log.popleft())
        active = self.query_one(TabbedContent).active
        if active == "unit":
            self._refresh_unit()
        elif active == "bus":
            width = self._width("#bus-view")
            lines = [
                line
                for f in bus_fields(self.rt, self.plans, self.bus_samples)
                for line in pack(f, width, "  ")
            ]
            self.query_one("#bus-view", Static).update("\n".join(lines))
        elif active == "plots":
            height = self.query_one("#plots-scroll").size.height
            self.query_one("#plots-view", Static).update(
                Text(f"unit {self.unit} (n/p select)\n", style="bold")
                + plots.render(
                    self.sup.units[self.unit],
                    self.sampler.traces[self.unit],
                    self.sup.clock(),
                    self._width("#plots-view"),
                    (height - 2) // len(SERIES),
                )
            )
        self.sub_title = (
            f"unit {self.unit}{' (all units)' if self.drive_all else ''} · "
            f"speed {self.speed:.2f} m/s, turn {self.turn:.2f} rad/s"
        )

    def _refresh_unit(self) -> None:
        name = self.unit
        unit = self.sup.units[name]
        self.query_one("#unit-head", Static).update(
            "\n".join(pack(detail_fields(self.sup, name), self._width("#unit-head")))
        )
        words = {"inputs": unit.inputs, **unit.words}
        titles = {
            "inputs": "inputs (commanded)",
            "control": "control (reported)",
            "io": "I/O (reported)",
        }
        for word in FLAG_BOXES:
            value = words.get(word)
            shown = "–" if value is None else f"0x{value:08X}"
            text = Text(f"{titles[word]} {shown}\n", style="bold")
            for on, label in flag_lines(unit.layout, word, value):
                text.append(label + "\n", style=SET_STYLE[word] if on else "dim")
            self.query_one(f"#flags-{word}", Static).update(text)
        text = Text("errors ✖ / alarms ▲\n", style="bold")
        for kind, label in fault_lines(words.get("error"), words.get("alarm")):
            style = {"error": "bold red", "alarm": "yellow"}.get(kind, "dim")
            text.append(label + "\n", style=style)
        self.query_one("#flags-faults", Static).update(text)

    # ------------------------------------------------------------ the runtime's side

    def call(self, fn: Callable[..., object], *args: object) -> None:
        """Change something on the runtime's side (its own thread when there is one)."""
        if self.bridge is None:
            fn(*args)
        else:
            self.bridge.call(fn, *args)

    async def run_remote(self, coro: Coroutine[Any, Any, T]) -> T:
        return await (self.bridge.run(coro) if self.bridge is not None else coro)

    def audit(self, action: str, unit: str | None = None, repeat_after: float = 0.0) -> None:
        """Into the audit trail; the same action again within ``repeat_after`` s (a held
        key repeating) only once."""
        now = time.monotonic()
        if (
            repeat_after
            and self._last_audit[0] == action
            and now - self._last_audit[1] < repeat_after
        ):
            return
        self._last_audit = (action, now)
        self.call(self.sup.audit, "tui", unit, action)

    @property
    def unit(self) -> str:
        return self.names[self.selected]

    def targets(self) -> tuple[str, ...]:
        commanded = [n for n in self.names if self.sup.units[n].cfg.role is Role.COMMAND]
        return tuple(commanded) if self.drive_all else (self.unit,)

    def say(self, text: str) -> None:
        self.query_one("#response", Static).update(text)

    # ------------------------------------------------------------ actions

    def action_estop(self) -> None:
        self.call(self.sup.emergency_stop)
        self.audit("key e-stop: EMERGENCY STOP")
        self.say("EMERGENCY STOP: every unit zero, START off — E (shift+e) to clear")
        self.refresh_view()

    def action_clear_estop(self) -> None:
        if not self.sup.estop:
            self.say("no emergency stop is latched")
            return

        def answer(yes: bool | None) -> None:
            self.audit(f"clear the emergency stop? {'yes' if yes else 'no'}")
            if yes:
                self.call(self.sup.clear_emergency_stop)
                self.say("e-stop cleared: give START again to move")

        self.push_screen(ConfirmScreen("Clear the emergency stop?"), answer)

    def action_drive(self, linear: int, angular: int) -> None:
        feed = self.source.feed
        targets = self.targets()
        why = operator.drive_refusal(self.sup, targets, bool(linear or angular))
        if why is not None:
            self.say(why)
            return
        if feed is None:
            return
        lin, ang = linear * self.speed, angular * self.turn
        feed.retarget(targets)
        feed.twist(lin, ang)
        what = f"drive {', '.join(targets)}: {lin:+.2f} m/s {ang:+.2f} rad/s"
        self.audit(what, repeat_after=2.0)
        self.say(f"{what} (hold the key; release = stop)")

    def action_speed(self, factor: float) -> None:
        speed_cap, turn_cap = operator.speed_caps(self.sup, self.targets())
        speed, turn = self.speed * factor, self.turn * factor
        self.speed, self.turn = min(speed, speed_cap), min(turn, turn_cap)
        capped = speed > speed_cap or turn > turn_cap
        note = " (capped at the velocity limit)" if capped else ""
        self.say(f"arrow speeds: {self.speed:.2f} m/s, {self.turn:.2f} rad/s{note}")

    def action_toggle_all(self) -> None:
        self.drive_all = not self.drive_all
        self.say(f"the arrows drive {', '.join(self.targets())}")

    def action_select(self, step: int) -> None:
        self.selected = (self.selected + step) % len(self.names)
        self.say(f"unit {self.unit} selected")
        self.refresh_view()

    def action_tab(self, tab: str) -> None:
        self.query_one(TabbedContent).active = tab
        self.refresh_view()

    def action_scroll(self, pages: int) -> None:
        active = self.query_one(TabbedContent).active
        pane = self.query_one(f"#{active}-scroll")
        if pages > 0:
            pane.scroll_page_down()
        else:
            pane.scroll_page_up()

    def action_plugin_key(self, index: int, char: int) -> None:
        key_input, keys = self.key_inputs[index]
        key = chr(char)
        self.audit(f"key {key!r}: {keys[key]}", repeat_after=2.0)
        key_input.press(key)

    def act(self, key: str, step: operator.Plan) -> None:
        """Carry out a plan: say why not, ask first, or send."""
        unit = self.unit
        if not step.commands:
            self.audit(f"key {key}: not done: {step.say}", unit)
            self.say(step.say)
            return
        if step.question is None:
            self.audit(f"key {key}: {'; '.join(step.commands)}", unit)
            self.run_commands(unit, step.commands)
            return

        def answer(yes: bool | None) -> None:
            asked = step.question.split("\n")[0] if step.question else ""
            self.audit(f"key {key}: {asked} → {'yes' if yes else 'no'}", unit)
            if yes:
                self.run_commands(unit, step.commands)
            else:
                self.say("nothing sent")

        self.push_screen(ConfirmScreen(step.question), answer)

    def action_flip(self, what: str) -> None:
        key = {"SERVO": "v", "START": "s", "BRAKE": "b", "TORQUE": "T"}[what]
        self.act(key, operator.toggle(self.sup, self.unit, what))

    def action_reset(self) -> None:
        self.act("r", operator.reset(self.sup, self.unit))

    def action_data_select(self) -> None:
        """Step both axes to the next preset table (written 7 = set #0 … 0 = #7 & STOP)."""
        name = self.unit
        if (why := operator.refusal(self.sup, name)) is not None:
            self.act("d", operator.Plan(say=why))
            return
        unit = self.sup.units[name]
        ay, _ = unit.layout.data_select(unit.inputs)
        written = (ay - 1) % 8
        command = f"SELECT {written} {written}"
        table = f"#{7 - written}" + (" & STOP" if written == 0 else "")
        question = f"{command} (data set {table}) on unit {name}?"
        self.act("d", operator.Plan((command,), question=question))

    def action_fault(self) -> None:
        cfg = self.sup.units[self.unit].cfg
        sim = self.rt.sims.get(cfg.bus)
        if sim is None:
            self.say("not a simulated unit")
            return
        drive = sim.drives[cfg.abh3_id]
        silent = not drive.silent
        self.call(setattr, drive, "silent", silent)
        what = f"simulated {self.unit} {'stops answering' if silent else 'answers again'}"
        self.audit(f"key f: {what}", self.unit)
        self.say(what)

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
    async def run_command(self, text: str) -> None:
        """The command line: the seed's exact response, and a note when the drive does not
        do what was asked (looked at once it had time to report)."""
        unit = self.unit
        response = await self.run_remote(self.sup.command(unit, text))
        self.audit(f":{text!r} → {response!r}", unit)
        self.say(f"{unit} ← {text!r} → {response!r}")
        if response == RESPONSE_OK:
            self.set_timer(1.0, lambda: self._explain(unit, text, response))

    def _explain(self, unit: str, text: str, response: str) -> None:
        state = self.sup.units[unit]
        control = reported(state)
        if control is None:
            return
        held = state.inputs & ~control
        off = [w for w in ("SERVO", "START") if held & operator.mask(state, w)]
        if off:
            why = (
                "errors present: r resets them"
                if state.words.get("error")
                else "after an error reset it waits to see SERVO off: v cycles it"
            )
            self.say(
                f"{unit} ← {text!r} → {response!r}, but the drive reports "
                f"{' '.join(off)} off ({why})"
            )

    @work(exclusive=False)
    async def run_commands(self, unit: str, commands: tuple[str, ...]) -> None:
        """One after the other, each once the drive answered a frame carrying the one
        before (so an error reset is a rising edge the drive saw)."""
        response = RESPONSE_OK
        for text in commands:
            response = await self.run_remote(self.sup.command(unit, text))
            if response != RESPONSE_OK:
                break
        self.say(f"{unit} ← {'; '.join(commands)} → {response!r}")

    def action_params(self) -> None:
        from abh3_supervisor.clients.tui.params import ParamScreen  # docs/parameters.md

        self.push_screen(ParamScreen(self, self.unit))

    def action_help(self) -> None:
        bindings = [b for b in self.BINDINGS if isinstance(b, Binding)]
        self.push_screen(HelpScreen(help_lines(bindings, self.plugin_keys)))

    def action_quit_safely(self) -> None:
        if isinstance(self.screen, ConfirmScreen):
            return

        def answer(yes: bool | None) -> None:
            self.audit(f"quit? {'yes' if yes else 'no'}")
            if yes:
                self.exit()

        self.push_screen(ConfirmScreen("Quit? Every unit gets zero, START and SERVO off."), answer)

    async def action_quit(self) -> None:
        """ctrl+q and the command palette's Quit ask too."""
        self.action_quit_safely()
