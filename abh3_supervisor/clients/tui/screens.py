"""Modal screens (confirmation of risky actions, the key help) and the input line."""

from __future__ import annotations

from typing import ClassVar

from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Button, Input, Static

ESTOP_KEY = "ctrl+e"  # the e-stop in every input line (and everywhere); `e` is text here
QUIT_KEY = "ctrl+c"  # asks to quit from every input line too (Input's own: copy)
NOT_TEXT = ("up", "down")  # the arrows drive the robot everywhere else: never while typing


class OperatorInput(Input):
    """An input line for typing: every printable key is text (``e`` too, so the app's
    priority ``e`` binding leaves the chain while it has the focus — Textual drops the
    bindings of keys the focused widget consumes), the up/down arrows do nothing rather
    than drive, and ``ctrl+e`` is never consumed (Input's own "end" key): the app's
    priority e-stop always sees it; nor ``ctrl+c`` (Input's copy): it asks to quit."""

    def check_consume_key(self, key: str, character: str | None) -> bool:
        if key in (ESTOP_KEY, QUIT_KEY):
            return False
        return key in NOT_TEXT or super().check_consume_key(key, character)


class ConfirmScreen(ModalScreen[bool]):
    """A yes/no question; No has the focus, so Enter never says yes by accident."""

    AUTO_FOCUS = "#no"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("y", "answer(True)", "yes"),
        Binding("n,escape", "answer(False)", "no"),
    ]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        with Vertical(id="dialog"):
            yield Static(self.question)
            with Horizontal():
                yield Button("Yes (y)", id="yes", variant="warning")
                yield Button("No (n, Esc)", id="no", variant="primary")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "yes")

    def action_answer(self, answer: bool) -> None:
        self.dismiss(answer)


class HelpScreen(ModalScreen[None]):
    AUTO_FOCUS = "#help"  # the arrows and page keys scroll it
    BINDINGS: ClassVar[list[BindingType]] = [Binding("escape,question_mark,q", "close", "close")]

    def __init__(self, lines: list[str]) -> None:
        super().__init__()
        self.lines = lines

    def compose(self) -> ComposeResult:
        with VerticalScroll(id="help"):
            yield Static("\n".join(self.lines))

    def action_close(self) -> None:
        self.dismiss(None)
