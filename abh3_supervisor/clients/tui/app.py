"""The Textual app: overview, unit detail, bus view, event log, plots, driving.

It is a client of the control socket (:mod:`abh3_supervisor.clients.link`): it shows the
state the service pushes (a :class:`Mirror`), and its keys become the socket's requests
— motion through the same input arbitration as the plugins (fresh for 0.5 s, then zero),
the command language, e-stop and clear. The app owns its terminal: input plugins of the
service that read keys get theirs from it (``keys``/``key``), after its own — e-stop,
tabs and quit always win. Every operator action goes to the supervisor's audit trail.
Who starts the service and what quitting does is :mod:`abh3_supervisor.clients.tui.run`'s.

It claims nothing it has not seen: ``ctrl+e`` is the e-stop on every screen and in every
input line, ``e`` everywhere but in an input line (there every printable key is text), and
the e-stop is shown latched only once the service confirms it;
without a connection every key that would send says it could NOT be sent; a state that
is no longer live is dimmed and says how old it is.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Mapping
from typing import Any, ClassVar

from rich.text import Text
from textual import events, work
from textual.actions import SkipAction
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Grid, VerticalScroll
from textual.css.query import NoMatches
from textual.keys import _character_to_key, format_key, key_to_character
from textual.screen import ModalScreen
from textual.widgets import Footer, Header, Input, RichLog, Static, TabbedContent, TabPane

from abh3_supervisor.clients.link import Link, LinkError, LinkLost
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui import operator, overview, plots
from abh3_supervisor.clients.tui.help import help_lines
from abh3_supervisor.clients.tui.hold import REPEAT_GAP_S, TICK_S, Drive, HeldKey
from abh3_supervisor.clients.tui.model import (
    SERIES,
    BusSample,
    Sampler,
    age,
    bus_fields,
    detail_fields,
    fault_lines,
    flag_lines,
    model_name,
    pack,
    reported,
)
from abh3_supervisor.clients.tui.screens import ConfirmScreen, HelpScreen, OperatorInput
from abh3_supervisor.config.model import Role
from abh3_supervisor.core.commands import RESPONSE_OK
from abh3_supervisor.core.planner import plan
from abh3_supervisor.core.robot import RobotConfig
from abh3_supervisor.params import table
from abh3_supervisor.service import protocol as rpc
from abh3_supervisor.service.view_pace import MIN_HZ

REFRESH_S = 0.1
STATE_HZ = 10  # what the service pushes: the refresh rate, no more
TABS = {"1": "overview", "2": "unit", "3": "bus", "4": "log", "5": "plots"}
FLAG_BOXES = ("inputs", "control", "io")
SET_STYLE = {"inputs": "bold cyan", "control": "bold green", "io": "bold green"}
WIDE_FLAGS = 130  # below this the flag boxes go two by two: no name is ever cut
DRIVE = f"(hold; release = stop within {REPEAT_GAP_S + TICK_S:.2g} s)"  # clients/tui/hold.py
STALE_S = 0.5  # five state pushes missed: what is shown is no longer live
ESTOP_CONFIRM_S = 0.5  # an e-stop the service has not confirmed by then is said to be so
HARDWARE = (
    "use the hardware emergency stop or switch the drives' power off. A supervisor that "
    "died stops nothing by itself: the drives stop on their own command-zero timeout once "
    "its frames cease"
)


def _slowed_note(slowed: dict[str, Any] | None) -> str:
    """The title bar's first words while the view gives way (a long title is cut at its
    end): by how much, and why — the CPU quota, or how late a bus step came."""
    if not slowed:
        return ""
    why = "CPU quota reached" if slowed.get("quota") else f"bus {slowed['late_ms']:g} ms late"
    return f"view 1/{slowed['by']} rate ({why}) · "


def styled(level: int, text: str) -> Text:
    style = "bold red" if level >= logging.ERROR else "yellow" if level >= logging.WARNING else ""
    return Text(f"{time.strftime('%H:%M:%S')} {text}", style=style)


class NotSent(LinkError):
    """Not connected: the request never left."""


def failed(exc: BaseException) -> str:
    """Why a request did not do what was asked: never sent, lost with the connection (then
    whether it acted is not known), or refused by the service."""
    if isinstance(exc, NotSent):
        return f"NOT SENT — {exc}"
    if isinstance(exc, LinkLost):
        return f"NOT CONFIRMED — {exc}"
    if "not switched on" in str(exc):  # the robot decision's refusal: the keys that help
        return f"refused: {exc} (v to switch SERVO on, s to switch START on)"
    return f"refused: {exc}"


class PaneHandler(logging.Handler):
    """Log records into the event log pane (any thread: a deque append is atomic)."""

    def __init__(self, pending: deque[Text]) -> None:
        super().__init__(logging.INFO)
        self.pending = pending

    def emit(self, record: logging.LogRecord) -> None:
        if record.name != "abh3":  # the supervisor's own event lines arrive as events
            self.pending.append(styled(record.levelno, record.getMessage()))


def _names(robots: tuple[RobotConfig, ...]) -> str:
    return ", ".join(r.name for r in robots)


def _b(key: str, action: str, short: str, long: str = "", show: bool = False) -> Binding:
    return Binding(key, action, short, show=show, tooltip=long or short)


class SupervisorApp(App[None]):
    CSS_PATH = "abh3.tcss"
    TITLE = "abh3-supervisor"
    AUTO_FOCUS = None  # keys go to the bindings; the command line takes focus only on ':'
    ENABLE_COMMAND_PALETTE = False  # its search line would take `e` from the e-stop

    ESTOP = "EMERGENCY STOP: every unit zero, START off, latched"
    BINDINGS: ClassVar[list[BindingType]] = [
        # priority: before any screen, question or input line; in an input line `e` is text
        # (OperatorInput consumes it, which takes this binding out of the chain), ctrl+e never
        Binding("ctrl+e", "estop", "E-STOP", priority=True, tooltip=ESTOP),
        Binding("e", "estop", "E-STOP", priority=True, tooltip=ESTOP, show=False),
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
        _b("o", "robot_switch", "robot on/off", "the selected unit's robot: on (asks) / off", True),
        _b("b", "flip('BRAKE')", "brake", "brake release, flipped (release asks)"),
        _b("T", "flip('TORQUE')", "torque", "torque (current) mode, flipped (on asks)"),
        _b("r", "reset", "error reset", "error reset, servo off after it (asks)"),
        _b("d", "data_select", "data select", "next data-select preset table (asks)"),
        _b("f", "fault", "sim: silence", "simulated units: stop answering / answer again"),
        # priority: taken as it comes, so the keys typed right after it are text (a
        # binding that waits its turn lets the next keys act: s, v, e); in an input line
        # it is text, and on a question or page it is left to them (SkipAction)
        Binding(
            "colon",
            "command",
            "command",
            priority=True,
            tooltip="command line, any case (VEL/CUR held while attached)",
        ),
        _b("P", "params", "parameters", "the unit's parameters: r read, w write one, f diff"),
        _b("1", "tab('overview')", "overview", "tab 1: every unit"),
        _b("2", "tab('unit')", "unit", "tab 2: the selected unit, every flag bit"),
        _b("3", "tab('bus')", "bus", "tab 3: frames/s, load, errors per bus"),
        _b("4", "tab('log')", "log", "tab 4: the event log and audit trail"),
        _b("5", "tab('plots')", "plots", "tab 5: plots of the selected unit (30 s)"),
        _b("pageup", "scroll(-1)", "page up", "scroll the tab up"),
        _b("pagedown", "scroll(1)", "page down", "scroll the tab down"),
        _b("question_mark", "help", "help", "this help", True),
        _b("q", "quit_safely", "quit", "quit (asks; stops the drives, or detaches)", True),
        # Textual's own ctrl+q (its quit asks too: action_quit), named here for the help
        _b("ctrl+q", "quit_safely", "quit", show=False),
        # the key a new user presses first: a priority binding, so no input line (where it
        # would copy) and no question or page takes it; it stops the arrows' drive at once
        Binding("ctrl+c", "quit_safely", "quit", show=False, priority=True, tooltip="quit"),
    ]
    QUIT = "Quit? Every unit gets zero, START and SERVO off."
    DETACH = (
        "Detach from the supervisor? It keeps running and so do the drives; motion this "
        "TUI commanded (arrow keys, VEL/CUR from the command line) stops at once."
    )

    def __init__(
        self,
        mirror: Mirror,
        link: Link | None,
        *,
        owner: bool = True,
        duration: float | None = None,
        plugin_keys: Mapping[str, dict[str, str]] | None = None,
        shows: str = "",
    ) -> None:
        """``owner``: this TUI started the service, and quitting stops it (and the drives);
        otherwise quitting only detaches. ``link`` None: no service (layout tests).
        ``shows``: the configuration file and socket, in the title."""
        super().__init__()
        self.title = f"{self.TITLE} · {shows}" if shows else self.TITLE
        self.duration = duration
        self.link = link
        self.owner = owner
        self.sup = mirror
        self.names = list(self.sup.units)
        self.selected = 0
        self.drive_all = False
        self.clock = time.monotonic  # the held arrow key's (a fake one in tests)
        self.hold = HeldKey()
        self.still: str | None = None  # why the held arrow moves nothing, as said
        self.speed, self.turn = 0.2, 0.5
        self.sampler = Sampler(self.sup)
        self.bus_samples: dict[str, BusSample] = {}
        self.plans = {p.bus: p for p in plan(mirror.config)}  # static: computed once
        self.pending_log: deque[Text] = deque(maxlen=2000)
        self._log_handler = PaneHandler(self.pending_log)
        self._last_audit: tuple[str, float] = ("", 0.0)
        self._sending: set[asyncio.Task[Any]] = set()
        self.silenced: set[str] = set()  # simulated units this TUI told to stop answering
        self.gone: str | None = None  # why the service is gone, once it is
        self.state_at = time.monotonic()  # when the service last pushed its state (ours)
        self.firmware: dict[str, str] = {}  # per unit, read once over the parameter channel
        self.plugin_keys = dict(plugin_keys or {})
        self._plugin_key_names: list[str] = list(self.plugin_keys)
        for i, keys in enumerate(self.plugin_keys.values()):
            for ch in keys:
                self.bind(_character_to_key(ch), f"plugin_key({i}, {ord(ch)})", show=False)
        if link is not None:
            link.on_notification = self._notified

    @classmethod
    def taken_keys(cls) -> list[str]:
        """The app's own keys, as characters: input plugins get other ones."""
        keys = (k for b in cls.BINDINGS if isinstance(b, Binding) for k in b.key.split(","))
        return sorted({key_to_character(k) or format_key(k) for k in keys})

    def _notified(self, method: str, params: dict[str, Any]) -> None:
        if method == "state" and self.sup.apply(params):
            self.state_at = time.monotonic()
            self.sampler.sample()
        elif method == "event":
            level = logging.getLevelName(str(params.get("level", "INFO")))
            text = str(params.get("text", ""))
            self.pending_log.append(styled(level if isinstance(level, int) else 20, text))

    # ------------------------------------------------------------ layout

    def compose(self) -> ComposeResult:
        yield Header()
        yield Static("EMERGENCY STOP LATCHED — E (shift+e) to clear", id="estop")
        yield Static(id="gone")
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
        yield OperatorInput(
            placeholder="command for the selected unit, any case, e.g. servo on on, vel 50 0 "
            "(ctrl+e is the e-stop; Esc closes)",
            id="cmdline",
        )
        yield Footer()

    def on_mount(self) -> None:
        root = logging.getLogger()
        self._saved_handlers = root.handlers[:]
        root.handlers = [self._log_handler]  # stderr is the screen now
        self.set_interval(REFRESH_S, self.refresh_view)
        self.set_interval(TICK_S, self.drive_tick)
        if self.link is not None:
            self.link.closed.add_done_callback(self._service_gone)
        self.refresh_view()
        if self.duration is not None:  # --duration: leave (and stop the drives) in time
            self.set_timer(self.duration, self.exit)

    def on_unmount(self) -> None:
        logging.getLogger().handlers = self._saved_handlers

    def on_resize(self, event: events.Resize) -> None:
        columns = 4 if event.size.width >= WIDE_FLAGS else 2
        with contextlib.suppress(NoMatches):
            self.query_one("#detail-flags", Grid).styles.grid_size_columns = columns

    def _service_gone(self, closed: asyncio.Future[str]) -> None:
        """Shown at once, and kept: what was on screen stays readable; q leaves."""
        if self.gone is not None or not self.is_running:
            return
        self.gone = closed.result() if not closed.cancelled() else "closed"
        if self.gone == rpc.STOPPING:  # an orderly stop: the supervisor stops its drives
            text = (
                f"NOT CONNECTED: {self.gone}: it sends zero and switches START, SERVO and "
                "the brake off on every unit itself, and its log says when each drive "
                "confirmed it. Nothing can be sent from here; if a drive still moves, use "
                "the hardware emergency stop. What is shown is stale. q quits"
            )
        else:
            text = (
                f"NOT CONNECTED: {self.gone}. Nothing can be sent from here, the e-stop "
                f"neither: {HARDWARE}. What is shown is stale. q quits"
            )
        with contextlib.suppress(NoMatches):
            self.query_one("#gone", Static).update(text)
            self.query_one("#gone").add_class("shown")
        self.pending_log.append(styled(logging.ERROR, text))
        self.refresh_view()

    # ------------------------------------------------------------ refresh

    def refresh_view(self) -> None:
        with contextlib.suppress(NoMatches):  # the app is closing: widgets already gone
            self._refresh()

    def _width(self, widget_id: str) -> int:
        width = self.query_one(widget_id).content_size.width
        return width if width > 0 else self.size.width - 2

    def stale_for(self) -> float | None:
        """How old what is shown is once it is no longer live; None while it is (and with
        no service at all: the layout tests)."""
        if self.link is None:
            return None
        seconds = time.monotonic() - self.state_at
        return seconds if self.gone is not None or seconds > self.stale_after() else None

    def stale_after(self) -> float:
        """``STALE_S``; while the service pushes less often (its pace gives way to late
        buses: service/view_pace.py), a push overdue by that much."""
        slowed = self.sup.slowed
        if not slowed:
            return STALE_S
        return min(float(slowed["by"]) / STATE_HZ, 1 / MIN_HZ) + STALE_S

    def _refresh(self) -> None:
        stale = self.stale_for()
        self.query_one(TabbedContent).set_class(stale is not None, "stale")
        banner = self.query_one("#estop", Static)
        banner.set_class(self.sup.estop, "latched")
        banner.update(
            "EMERGENCY STOP LATCHED — E (shift+e) to clear"
            if stale is None
            else f"emergency stop latched as of {age(stale)} ago (stale)"
        )
        self.query_one("#table", Static).update(
            overview.render(
                self.sup,
                self.names,
                self.selected,
                self._width("#table"),
                stale,
                self.arrows_line(),
            )
        )
        log = self.query_one("#log-scroll", RichLog)
        while self.pending_log:
            log.write(self.pending_log.popleft())
        active = self.query_one(TabbedContent).active
        if active == "unit":
            self._refresh_unit(stale)
        elif active == "bus":
            width = self._width("#bus-view")
            lines = [f"STALE: these figures are {age(stale)} old"] if stale is not None else []
            lines += [
                line
                for f in bus_fields(self.sup, self.plans, self.bus_samples)
                for line in pack(f, width, "  ")
            ]
            self.query_one("#bus-view", Static).update("\n".join(lines))
        elif active == "plots":
            height = self.query_one("#plots-scroll").size.height
            head = f"unit {self.unit} (n/p select) · velocity model "
            head += model_name(self.sup.units[self.unit])
            if stale is not None:
                head += f" · STALE: no samples for {age(stale)}"
            self.query_one("#plots-view", Static).update(
                Text(head + "\n", style="bold")
                + plots.render(
                    self.sup.units[self.unit],
                    self.sampler.traces[self.unit],
                    self.sup.t,
                    self._width("#plots-view"),
                    (height - 2) // len(SERIES),
                )
            )
        robots = self.arrow_robots()
        arrows = "" if all(r.implicit for r in robots) else f" · arrows: {_names(robots)}"
        self.sub_title = _slowed_note(self.sup.slowed) + (
            f"unit {self.unit}{' (all units)' if self.drive_all else ''}{arrows} · "
            f"speed {self.speed:.2f} m/s, turn {self.turn:.2f} rad/s"
        )

    def _refresh_unit(self, stale: float | None) -> None:
        name = self.unit
        unit = self.sup.units[name]
        if name not in self.firmware and unit.online and self._not_connected() is None:
            self.firmware[name] = "…"  # asked once per unit, while the tab shows it
            self.ask_firmware(name)
        fields = detail_fields(self.sup, name, self.firmware.get(name), stale)
        self.query_one("#unit-head", Static).update(
            "\n".join(pack(fields, self._width("#unit-head")))
        )
        words = {"inputs": unit.inputs, **unit.words}
        titles = {
            "inputs": "inputs (commanded)",
            "control": "control (reported)",
            "io": "I/O (reported)",
        }
        silent = unit.online is False  # what it reported is its last word, greyed
        last = "\nas last reported: no answer now" if silent else ""
        for word in FLAG_BOXES:
            value = words.get(word)
            shown = "–" if value is None else f"0x{value:08X}"
            old = last if word != "inputs" else ""
            text = Text(f"{titles[word]} {shown}{old}\n", style="bold")
            for on, label in flag_lines(unit.layout, word, value):
                style = SET_STYLE[word] if on and not old else "dim"
                text.append(label + "\n", style=style)
            self.query_one(f"#flags-{word}", Static).update(text)
        text = Text(f"errors ✖ / alarms ▲{last}\n", style="bold")
        for kind, label in fault_lines(words.get("error"), words.get("alarm"), unit.cfg.role):
            style = {"error": "bold red", "alarm": "yellow"}.get(kind, "dim")
            text.append(label + "\n", style="dim" if silent else style)
        self.query_one("#flags-faults", Static).update(text)

    # ------------------------------------------------------------ the service's side

    def _not_connected(self) -> str | None:
        if self.link is None or self.gone is not None:
            return f"not connected to the supervisor: {self.gone or 'no service'}"
        return None

    def connected(self) -> bool:
        """Connected; otherwise says at once that nothing was sent."""
        why = self._not_connected()
        if why is not None:
            self.say(f"NOT SENT — {why}")
        return why is None

    async def request(self, method: str, **params: Any) -> Any:
        """A request whose answer matters; :class:`LinkError` when refused or not connected."""
        if (why := self._not_connected()) is not None:
            raise NotSent(why)
        assert self.link is not None
        return await self.link.call(method, **params)

    def send(self, method: str, **params: Any) -> None:
        """A request whose answer only matters when it is a refusal (said at once)."""
        if not self.connected():
            return
        task = asyncio.ensure_future(self.request(method, **params))
        self._sending.add(task)
        task.add_done_callback(self._sent)

    def _sent(self, task: asyncio.Task[Any]) -> None:
        self._sending.discard(task)
        exc = None if task.cancelled() else task.exception()
        if isinstance(exc, LinkError):
            with contextlib.suppress(NoMatches):
                self.say(failed(exc))

    async def command_text(self, unit: str, text: str) -> tuple[str, str]:
        """The seed's exact answer to one command, or why there is none; and the
        service's note when it clamped the value (``''`` otherwise)."""
        try:
            reply = await self.request("command", unit=unit, text=text)
        except LinkError as exc:
            return failed(exc), ""
        notes = reply.get("clamped") or {}  # absent from services before the clamp notes
        return str(reply["response"]), str(notes.get(unit, ""))

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
        if self._not_connected() is None:
            self.send("audit", unit=unit, action=action)

    @property
    def unit(self) -> str:
        return self.names[self.selected]

    def targets(self) -> tuple[str, ...]:
        commanded = [n for n in self.names if self.sup.units[n].cfg.role is Role.COMMAND]
        return tuple(commanded) if self.drive_all else (self.unit,)

    def arrow_robots(self) -> tuple[RobotConfig, ...]:
        """The robots the arrows drive: the selected unit's (every one's with ``a``)."""
        return operator.robots_of(self.sup, self.targets())

    def arrows_line(self) -> str | None:
        """What the arrows drive, for the overview, when the file declares robots (with
        one-drive robots only, the selected unit ▶ says it)."""
        robots = self.arrow_robots()
        if all(r.implicit for r in robots):
            return None
        return f"the arrows drive {operator.arrows_drive(robots)}"

    def say(self, text: str) -> None:
        # a line due after the app began closing (a timer's, an answer's) has nowhere to go
        with contextlib.suppress(NoMatches):
            self.query_one("#response", Static).update(text)

    # ------------------------------------------------------------ actions

    def action_estop(self) -> None:
        """Sent before anything else; then every question, page and input line closes
        (a question is answered no) so the outcome is in sight. Shown latched only once
        the service confirms it."""
        self.hold.stop()
        why = self._not_connected()
        if why is None:
            self.confirm_estop(asyncio.ensure_future(self.request("estop")))
        while isinstance(self.screen, ModalScreen):
            self.screen.dismiss(None)
        self.key_escape()
        if why is not None:
            self.say(f"E-STOP NOT SENT — {why}: {HARDWARE}.")
            self.pending_log.append(styled(logging.ERROR, f"key e-stop: NOT SENT ({why})"))
            return
        self.say("EMERGENCY STOP sent: waiting for the supervisor to confirm it …")

    @work(exclusive=False)
    async def confirm_estop(self, sent: asyncio.Future[Any]) -> None:
        try:
            await asyncio.wait_for(sent, ESTOP_CONFIRM_S)
        except (LinkError, TimeoutError) as exc:
            why = str(exc) or f"no answer within {ESTOP_CONFIRM_S:g} s"
            self.say(f"E-STOP NOT CONFIRMED by the supervisor ({why}): {HARDWARE}.")
            self.pending_log.append(styled(logging.ERROR, f"key e-stop: NOT CONFIRMED ({why})"))
            return
        self.sup.estop = True  # confirmed: shown at once, the next state says it too
        self.refresh_view()
        self.say(
            "EMERGENCY STOP latched: every unit zero, START off, then SERVO and brake off "
            "once stopped — E (shift+e) to clear"
        )
        self.audit("key e-stop: EMERGENCY STOP")

    def action_clear_estop(self) -> None:
        if not self.connected():
            return
        foreign = any((u.foreign or {}).get("stopped") for u in self.sup.units.values())
        if not self.sup.estop and not foreign:
            self.say("no emergency stop is latched")
            return

        # the stop another host caused (core/foreign.py) is cleared the same way, by the
        # service only once that host has been quiet: what stands is said in the notices
        what = "the emergency stop" if self.sup.estop else "the stop by another host"

        def answer(yes: bool | None) -> None:
            self.audit(f"clear {what}? {'yes' if yes else 'no'}")
            if yes:
                self.send("clear_estop")
                done = "e-stop cleared" if self.sup.estop else "asked to clear (see the notices)"
                self.say(f"{done}: give START again to move")

        self.push_screen(ConfirmScreen(f"Clear {what}?"), answer)

    def action_drive(self, linear: int, angular: int) -> None:
        """An arrow's press or auto-repeat holds its twist (re-sent by :meth:`drive_tick`
        until the key is taken as released); space stops at once."""
        if not self.connected():
            self.hold.stop()
            return
        robots = self.arrow_robots()  # each robot as a whole: all its drives together
        units = operator.robot_units(robots)
        moving = bool(linear or angular)
        why = operator.drive_refusal(self.sup, units, moving)
        if why is not None or not moving:
            self.hold.stop()
        if why is not None:
            self.say(why)
            return
        lin, ang = linear * self.speed, angular * self.turn
        names = tuple(r.name for r in robots)
        if not moving or self.hold.press(Drive(names, lin, ang), self.clock()):
            self.send("twist", robots=list(names), linear_x=lin, angular_z=ang)
        what = f"drive {operator.arrows_drive(robots)}: {lin:+.2f} m/s {ang:+.2f} rad/s"
        self.audit(what, repeat_after=2.0)
        self.still = operator.stillness(self.sup, units) if moving else None
        self.say(self.still or f"{what} (hold the key; release = stop)")

    def drive_tick(self) -> None:
        """The held twist again while its key is held, zero once it is taken as released."""
        due = self.hold.tick(self.clock())
        if due is None:
            return
        drive, held = due
        robots = tuple(self.sup.config.robots[name] for name in drive.robots)
        if held and operator.drive_refusal(self.sup, operator.robot_units(robots), True):
            self.hold.stop()  # e.g. latched by another client: its own notice says so
            return
        if self._not_connected() is not None:  # the banner says so; no line per tick
            self.hold.stop()
            return
        lin, ang = (drive.linear, drive.angular) if held else (0.0, 0.0)
        self.send("twist", robots=list(drive.robots), linear_x=lin, angular_z=ang)
        if not held and self.still is None:  # why nothing moved stays in sight
            self.say(f"drive {operator.arrows_drive(robots)}: key released, stop sent")

    def action_speed(self, factor: float) -> None:
        speed_cap, turn_cap = operator.speed_caps(self.sup, self.targets())
        speed, turn = self.speed * factor, self.turn * factor
        self.speed, self.turn = min(speed, speed_cap), min(turn, turn_cap)
        capped = speed > speed_cap or turn > turn_cap
        note = " (capped at the robot's limits)" if capped else ""
        self.say(f"arrow speeds: {self.speed:.2f} m/s, {self.turn:.2f} rad/s{note}")

    def action_toggle_all(self) -> None:
        self.drive_all = not self.drive_all
        self.say(f"the arrows drive {operator.arrows_drive(self.arrow_robots())}")

    def action_select(self, step: int) -> None:
        self.selected = (self.selected + step) % len(self.names)
        line = self.arrows_line()
        self.say(f"unit {self.unit} selected" + (f" ({line})" if line else ""))
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
        if not self.connected():
            return
        name = self._plugin_key_names[index]
        key = chr(char)
        self.audit(f"key {key!r}: {self.plugin_keys[name][key]}", repeat_after=2.0)
        self.send("key", source=name, key=key)

    def act(self, key: str, step: operator.Plan) -> None:
        """Carry out a plan: say why not, ask first, or send."""
        unit = self.unit
        if not self.connected():  # asking first would promise what cannot be done
            return
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
            elif yes is False:  # None: closed by the e-stop, which says what it did
                self.say("nothing sent")

        self.push_screen(ConfirmScreen(step.question), answer)

    def action_flip(self, what: str) -> None:
        key = {"SERVO": "v", "START": "s", "BRAKE": "b", "TORQUE": "T"}[what]
        self.act(key, operator.toggle(self.sup, self.unit, what))

    def action_reset(self) -> None:
        self.act("r", operator.reset(self.sup, self.unit))

    def action_robot_switch(self) -> None:
        """The selected unit's robot as one act (the service's enable/disable): off at once
        while it is ready or any of its drives is commanded on; otherwise on, asked first.
        The answer names the drive that did not follow (docs/safety.md)."""
        if not self.connected():
            return
        robot = self.sup.config.robot_of(self.unit)
        if robot is None:
            self.say(f"unit {self.unit} drives no robot")
            return
        servo = any(
            self.sup.units[u].inputs & (self.sup.units[u].layout.servo.both) for u in robot.units
        )
        ready = robot.name in self.sup.robots and self.sup.robots[robot.name] is None
        if ready or servo:
            self.audit(f"key o: disable robot {robot.name}", self.unit)
            self.run_worker(self._robot_switch(robot.name, on=False))
            return
        drives = ", ".join(robot.units)
        question = (
            f"Switch robot {robot.name} on? SERVO and START on every wheel axis of {drives}; "
            "it moves only when driven."
        )

        def answer(yes: bool | None) -> None:
            self.audit(f"key o: {question} → {'yes' if yes else 'no'}", self.unit)
            if yes:
                self.run_worker(self._robot_switch(robot.name, on=True))
            elif yes is False:
                self.say("nothing sent")

        self.push_screen(ConfirmScreen(question), answer)

    async def _robot_switch(self, robot: str, *, on: bool) -> None:
        try:
            reply = await self.request("enable" if on else "disable", robot=robot)
        except LinkError as exc:
            self.say(failed(exc))
            return
        not_ready = reply.get("not_ready") or {}
        if not on:
            self.say(f"robot {robot}: SERVO and START off")
        elif robot in not_ready:
            self.say(f"robot {robot} switched on, but not ready: {not_ready[robot]}")
        else:
            self.say(f"robot {robot} READY: every drive reports SERVO and START on")

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
        if not self.connected():
            return
        cfg = self.sup.units[self.unit].cfg
        if not self.sup.buses[cfg.bus].simulated:
            self.say("not a simulated unit")
            return
        silent = self.unit not in self.silenced
        self.silenced ^= {self.unit}
        self.send("simulate", unit=self.unit, silent=silent)
        what = f"simulated {self.unit} {'stops answering' if silent else 'answers again'}"
        self.audit(f"key f: {what}", self.unit)
        self.say(what)

    def action_command(self) -> None:
        if isinstance(self.screen, ModalScreen):
            raise SkipAction()
        if not self.connected():
            return
        cmdline = self.query_one("#cmdline", Input)
        cmdline.add_class("open")
        self.screen.set_focus(cmdline)  # at once: Widget.focus waits for the queued keys

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
        response, clamped = await self.command_text(unit, text)
        note = f" · {clamped}" if clamped else ""  # the service's, beside the seed's answer
        self.audit(f":{text!r} → {response!r}{note}", unit)
        answer = f"{unit} ← {text!r} → {response!r}{note}"
        self.say(answer)
        if response == RESPONSE_OK:
            self.set_timer(1.0, lambda: self._explain(unit, answer))

    def _explain(self, unit: str, answer: str) -> None:
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
            self.say(f"{answer}, but the drive reports {' '.join(off)} off ({why})")

    @work(exclusive=False)
    async def ask_firmware(self, unit: str) -> None:
        """The drive's firmware version (TelABH3 identity, BI 0x2): a read, moves nothing."""
        try:
            reply = await self.request("param_identity", unit=unit, address=table.FIRMWARE_VERSION)
            self.firmware[unit] = str(reply["text"])
        except LinkError as exc:
            self.firmware[unit] = "unknown"
            self.pending_log.append(styled(logging.WARNING, f"{unit}: firmware version: {exc}"))

    @work(exclusive=False)
    async def run_commands(self, unit: str, commands: tuple[str, ...]) -> None:
        """One after the other, each once the drive answered a frame carrying the one
        before (so an error reset is a rising edge the drive saw)."""
        response = RESPONSE_OK
        for text in commands:  # switches only: nothing a limit clamps
            response, _ = await self.command_text(unit, text)
            if response != RESPONSE_OK:
                break
        self.say(f"{unit} ← {'; '.join(commands)} → {response!r}")

    def action_params(self) -> None:
        from abh3_supervisor.clients.tui.params import ParamScreen  # docs/parameters.md

        if self.connected():
            self.push_screen(ParamScreen(self, self.unit))

    def action_help(self) -> None:
        bindings = [b for b in self.BINDINGS if isinstance(b, Binding)]
        self.push_screen(HelpScreen(help_lines(bindings, self.plugin_keys)))

    def quitting(self) -> bool:
        """The quit (or detach) question is open."""
        screen = self.screen
        return isinstance(screen, ConfirmScreen) and screen.question in (self.QUIT, self.DETACH)

    def action_quit_safely(self) -> None:
        """q, ctrl+q and ctrl+c: the arrows' drive stops now; any other question (= no),
        page or input line closes, and the quit question is asked (once)."""
        drive = self.hold.drive
        self.hold.stop()
        if drive is not None and self._not_connected() is None:
            self.send("twist", robots=list(drive.robots), linear_x=0.0, angular_z=0.0)
            self.say(f"drive {', '.join(drive.robots)}: stop sent")
        if self.quitting():
            return
        while isinstance(self.screen, ModalScreen):
            self.screen.dismiss(None)
        self.key_escape()

        def answer(yes: bool | None) -> None:
            self.audit(f"{'quit' if self.owner else 'detach'}? {'yes' if yes else 'no'}")
            if yes:
                self.hold.stop()
                if not self.owner:  # the motion goes now, not when the UI has wound down
                    self.send("release")
                self.exit()

        if self.gone is not None:  # nothing left to stop from here
            self.exit()
            return
        self.push_screen(ConfirmScreen(self.QUIT if self.owner else self.DETACH), answer)

    async def action_quit(self) -> None:
        """ctrl+q and the command palette's Quit ask too."""
        self.action_quit_safely()
