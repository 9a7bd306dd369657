"""``abh3 fleet``: the Textual view of every robot on the broker, with the fleet e-stop.

The app holds no network: its ``Session`` (session.py) drains a ``Link`` (the paho client
in ``broker.py``, a fake in the tests) into the model and the commander, which decide
what is shown, and sends what it publishes. Ten times a second it ticks and repaints.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from typing import ClassVar

from textual.app import App, ComposeResult, SuspendNotSupported
from textual.binding import Binding, BindingType
from textual.containers import VerticalScroll
from textual.widgets import Footer, Static

from abh3_supervisor.clients.fleet.commands import Commander, Sent
from abh3_supervisor.clients.fleet.model import FleetModel
from abh3_supervisor.clients.fleet.session import Link, Session
from abh3_supervisor.clients.fleet.view import SELECTED, body, head
from abh3_supervisor.clients.tui.screens import ConfirmScreen

TICK_S = 0.1


def attach_argv(address: str) -> list[str] | None:
    """``abh3 tui --connect ADDRESS`` for a robot's ``status.attach``; None unless it is
    an ``ssh://`` address (what a robot publishes is never a command line of its own)."""
    if not address.startswith("ssh://") or any(c.isspace() for c in address):
        return None
    return [sys.executable, "-m", "abh3_supervisor", "tui", "--connect", address]


class FleetApp(App[int]):
    CSS_PATH = "../tui/abh3.tcss"  # the TUI's dialogs
    TITLE = "abh3 fleet"
    ENABLE_COMMAND_PALETTE = False  # its search line would take `e` from the e-stop
    BINDINGS: ClassVar[list[BindingType]] = [
        # before the list's own scrolling: the selection moves, the list follows it
        Binding("up", "move(-1)", "previous robot", show=False, priority=True),
        Binding("down", "move(1)", "next robot", show=False, priority=True),
        # priority: before any question on top (the view has no text input to type `e` in)
        Binding("ctrl+e", "estop", "e-stop robot", priority=True, show=False),
        Binding("e", "estop", "e-stop robot", priority=True),
        Binding("E", "estop_all", "e-stop ALL"),
        Binding("c", "clear", "clear robot"),
        Binding("C", "clear_all", "clear all"),
        Binding("a", "attach", "attach TUI"),
        Binding("q", "quit", "quit"),
    ]

    def __init__(
        self,
        model: FleetModel,
        commander: Commander,
        link: Link,
        reason: str,
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__()
        self.session = Session(model, commander, link, reason, clock)
        self.selected: str | None = None
        # two texts, repainted: whatever screen is on top; the head never scrolls away
        self.head = Static(id="fleet-head")
        self.shown = Static(id="fleet")
        self.scroller = VerticalScroll()

    def compose(self) -> ComposeResult:
        yield self.head
        with self.scroller:
            yield self.shown
        yield Footer()

    def on_mount(self) -> None:
        self.tick()
        self.set_interval(TICK_S, self.tick)

    def tick(self) -> None:
        self.session.tick()
        if self.selected not in self.session.model.robots:
            self.selected = min(self.session.model.robots, default=None)
        now = self.session.clock()
        latest = self.session.commander.latest()
        model, connected = self.session.model, self.session.link.connected
        broker = self.session.link.describe(now)
        summary = latest.summary() if latest else None
        self.head.update(head(model, broker, summary, connected=connected))
        shown = body(model, now, self.selected, connected=connected)
        self.shown.update(shown)
        self._follow(shown.plain)

    def _follow(self, plain: str) -> None:
        """Scroll the list so that the selected robot's line is in sight."""
        lines = plain.splitlines()
        row = next((i for i, line in enumerate(lines) if line.startswith(SELECTED)), None)
        if row is None:
            return
        top, height = round(self.scroller.scroll_y), self.scroller.scrollable_content_region.height
        if row < top:
            self.scroller.scroll_to(y=row, animate=False)
        elif height and row >= top + height:
            self.scroller.scroll_to(y=row - height + 1, animate=False)

    # -- keys ------------------------------------------------------------------------

    def action_move(self, step: int) -> None:
        order = sorted(self.session.model.robots)
        if not order:
            return
        at = order.index(self.selected) if self.selected in order else 0
        self.selected = order[max(0, min(len(order) - 1, at + step))]
        self.tick()

    def action_estop(self) -> None:
        if self.selected is None:
            self.notify("no robot to e-stop: none seen yet", severity="warning")
            return
        self.send(self.selected, clear=False)  # at once: an e-stop asks nothing

    def action_estop_all(self) -> None:
        count = len(self.session.model.robots)
        question = (
            f"E-STOP ALL: every robot subscribed to {self.session.commander.prefix}/all/cmd/estop "
            f"({count} shown here) latches its e-stop. Send?"
        )
        self.push_screen(ConfirmScreen(question), self._then(None, clear=False))

    def action_clear(self) -> None:
        if self.selected is None:
            self.notify("no robot to clear: none seen yet", severity="warning")
            return
        question = (
            f"Clear the e-stop of {self.selected}? Nothing moves until START and motion are "
            "given again, by whoever owns it."
        )
        self.push_screen(ConfirmScreen(question), self._then(self.selected, clear=True))

    def action_clear_all(self) -> None:
        question = (
            f"Clear the e-stop of ALL robots subscribed to {self.session.commander.prefix}/all/cmd/"
            "estop_clear? Nothing moves until START and motion are given again."
        )
        self.push_screen(ConfirmScreen(question), self._then(None, clear=True))

    def _then(self, target: str | None, *, clear: bool) -> Callable[[bool | None], None]:
        def answered(yes: bool | None) -> None:
            if yes:
                self.send(target, clear=clear)

        return answered

    def send(self, target: str | None, *, clear: bool) -> Sent:
        sent = self.session.send(target, clear=clear)
        self.tick()
        return sent

    def action_attach(self) -> None:
        robot = self.session.model.robots.get(self.selected or "")
        if robot is None:
            self.notify("no robot selected", severity="warning")
            return
        if robot.attach is None:
            self.notify(
                f"{robot.fleet_id} publishes no attach address (its mqtt plugin's `attach` "
                "setting): no TUI to attach",
                severity="warning",
            )
            return
        argv = attach_argv(robot.attach)
        if argv is None:
            self.notify(
                f"{robot.fleet_id}: attach {robot.attach!r} is not ssh://…", severity="error"
            )
            return
        code = self.run_attached(argv)
        if code:
            self.notify(f"abh3 tui --connect {robot.attach} ended with {code}", severity="warning")

    def run_attached(self, argv: list[str]) -> int:
        """The robot's TUI on this terminal, this app suspended until it ends."""
        try:
            with self.suspend():
                return subprocess.run(argv, check=False).returncode
        except SuspendNotSupported:
            self.notify("this terminal cannot hand itself over: run " + " ".join(argv[3:]))
            return 0
