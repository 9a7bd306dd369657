"""The parameter page of one unit (key ``P``): read all, write one, diff against a file.

Every request goes over the control socket to the service's :class:`ParamOps` (the same
code as ``abh3 param``): a write asks the drive whether its servo is off, now, before the
operator's question; the service asks again at the write and logs the old and the new
value. The page reads in a worker, so the screen — and the e-stop — stay live while a slow
drive answers. ``e`` is the e-stop here as everywhere but in the value's input line
(the app's priority binding; ``ctrl+e`` there, where every printable key is text, so
``1e3`` is typed as it is), writing is ``w`` or Enter, and the file to diff against is
picked, not typed.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from textual.app import ComposeResult
from textual.await_complete import AwaitComplete
from textual.binding import Binding, BindingType
from textual.containers import Vertical
from textual.screen import ModalScreen
from textual.widgets import DataTable, DirectoryTree, Input, Static

from abh3_supervisor.clients.tui.screens import ConfirmScreen, OperatorInput
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.params import files, table
from abh3_supervisor.service.param_ops import shown

if TYPE_CHECKING:
    from abh3_supervisor.clients.tui.app import SupervisorApp

COLUMNS = ("address", "name", "value", "word", "file")
HINT = "r read all · w or Enter write the selected one · f diff against a file · Esc close"


def parameter_file(path: Path) -> bool:
    try:
        files.format_of(path)
    except Abh3Error:
        return False
    return True


class ParameterFiles(DirectoryTree):
    """Directories and parameter files only, under the directory the TUI started in."""

    def filter_paths(self, paths: Iterable[Path]) -> Iterable[Path]:
        return [p for p in paths if p.is_dir() or parameter_file(p)]


class ParamScreen(ModalScreen[None]):
    DEFAULT_CSS = """
    ParamScreen { align: center middle; }
    #params { width: 100; max-width: 98%; height: 90%; border: thick $primary;
              background: $surface; padding: 0 1; }
    #params DataTable { height: 1fr; }
    #params-input, #params-files { display: none; }
    #params-input.open { display: block; }
    #params-files.open { display: block; height: 12; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape", "close", "close"),
        Binding("r", "read_all", "read all"),
        # priority: the value typed right after it goes into its input line (in there
        # `w` is text: Input consumes it)
        Binding("w", "edit", "write the selected parameter", priority=True),
        Binding("f", "diff", "diff against a file"),
    ]

    def __init__(self, owner: SupervisorApp, unit: str) -> None:
        super().__init__()
        self.owner, self.unit = owner, unit
        self.words: dict[int, int] = {}
        self.mode = ""  # what is open below the table: "edit" (the input line) or "diff"
        self.editing = 0

    def compose(self) -> ComposeResult:
        with Vertical(id="params"):
            yield Static(f"parameters of {self.unit}", id="params-head")
            yield DataTable(id="params-table", cursor_type="row")
            yield OperatorInput(id="params-input")
            yield Static(HINT, id="params-status")

    def on_mount(self) -> None:
        grid = self.query_one(DataTable)
        for column in COLUMNS:
            grid.add_column(column, key=column)
        for e in table.PARAMETERS:
            grid.add_row(f"0x{e.address:04X}", e.name, "…", "", "", key=str(e.address))
        grid.focus()
        self.action_read_all()

    def say(self, text: str) -> None:
        self.query_one("#params-status", Static).update(text)

    def dismiss(self, result: None = None) -> AwaitComplete:
        """Reads stop first: a reply landing on a page being taken down would find no
        table (the e-stop closes this page at any moment)."""
        self.workers.cancel_node(self)
        return super().dismiss(result)

    # ------------------------------------------------------------ reading

    def action_read_all(self) -> None:
        self.run_worker(self._read_all(), exclusive=True, group="params")

    async def _read_all(self) -> None:
        head = self.query_one("#params-head", Static)
        try:
            reply = await self.owner.request(
                "param_identity", unit=self.unit, address=table.FIRMWARE_VERSION
            )
            firmware = reply["text"]
            head.update(f"parameters of {self.unit} · firmware {firmware}")
            for n, e in enumerate(table.PARAMETERS, 1):
                reply = await self.owner.request(
                    "param_read", unit=self.unit, address=e.address, command="CP"
                )
                word = int(reply["word"])
                self._show(e.address, word)
                self.say(f"reading {n}/{len(table.PARAMETERS)}")
        except Abh3Error as exc:
            self.say(f"stopped: {exc}")
            return
        self.say(f"{len(table.PARAMETERS)} parameters read · {HINT}")

    def _show(self, address: int, word: int) -> None:
        self.words[address] = word
        grid = self.query_one(DataTable)
        # the columns grow to what they hold (a word is always all eight digits)
        grid.update_cell(str(address), "value", shown(address, word), update_width=True)
        grid.update_cell(str(address), "word", f"{word:08X}", update_width=True)

    # ------------------------------------------------------------ the input line, the files

    def _ask(self, placeholder: str) -> None:
        self.mode = "edit"
        line = self.query_one("#params-input", Input)
        line.placeholder, line.value = placeholder, ""
        line.add_class("open")
        self.set_focus(line)  # at once: the keys typed right after `w` are the value

    def _close_input(self) -> None:
        self.query_one("#params-input", Input).remove_class("open")
        for tree in self.query(ParameterFiles):
            tree.remove()
        self.mode = ""
        self.query_one(DataTable).focus()

    def action_close(self) -> None:
        if self.mode:
            self._close_input()
        else:
            self.dismiss(None)

    def on_input_submitted(self, event: Input.Submitted) -> None:
        event.stop()  # ours: the app's command line must never see it
        mode, text = self.mode, event.value.strip()
        self._close_input()
        if text and mode == "edit":
            self._confirm_edit(text)

    def on_directory_tree_file_selected(self, event: DirectoryTree.FileSelected) -> None:
        event.stop()
        self._close_input()
        self._diff(event.path)

    # ------------------------------------------------------------ writing

    def on_data_table_row_selected(self, event: DataTable.RowSelected) -> None:
        self.action_edit()  # Enter on a row

    def action_edit(self) -> None:
        grid = self.query_one(DataTable)
        if not grid.row_count:
            return
        address = int(grid.coordinate_to_cell_key(grid.cursor_coordinate).row_key.value or 0)
        if address not in self.words:
            self.say(f"0x{address:04X} is not read yet: r reads all")
            return
        self.editing = address
        now = shown(address, self.words[address])
        self._ask(f"new value of 0x{address:04X} {table.label(address)} (now {now})")

    def _confirm_edit(self, text: str) -> None:
        address = self.editing
        try:
            word = table.to_word(float(text), table.kind_of(address))
        except (ValueError, Abh3Error) as exc:
            self.say(f"'{text}': {exc}")
            return
        self.run_worker(self._ask_to_write(address, word), group="params")

    async def _ask_to_write(self, address: int, word: int) -> None:
        """The servo is asked of the drive before the question (and again by the write):
        a question the service would refuse is never asked."""
        self.say("asking the drive whether its servo is off …")
        try:
            servo = (await self.owner.request("param_servo", unit=self.unit))["servo"]
        except Abh3Error as exc:
            self.say(f"not written: {exc}")
            return
        if servo is not False:
            why = "reports its servo ON" if servo else "did not answer whether its servo is on"
            self.say(f"not written: the drive {why} (asked now); SERVO OFF first")
            return
        old = shown(address, self.words[address])
        new = shown(address, word)
        question = f"Write {self.unit} 0x{address:04X} {table.label(address)}: {old} → {new}?"
        self.say("the drive reports its servo off")

        def answer(yes: bool | None) -> None:
            if yes:
                self.run_worker(self._write(address, word), group="params")
            elif yes is False:  # None: closed by the e-stop, which closes this page too
                self.say("not written")

        self.owner.push_screen(ConfirmScreen(question), answer)

    async def _write(self, address: int, word: int) -> None:
        try:
            reply = await self.owner.request(
                "param_write", unit=self.unit, address=address, word=word
            )
            back = int(reply["new"])
        except Abh3Error as exc:
            self.say(f"not written: {exc}")
            return
        self._show(address, back)
        self.say(f"written: 0x{address:04X} {table.label(address)} = {shown(address, back)}")

    # ------------------------------------------------------------ diff

    def action_diff(self) -> None:
        """A file picked under the current directory: a path could not be typed, as it
        may hold an ``e``."""
        self._close_input()
        self.mode = "diff"
        tree = ParameterFiles(Path.cwd(), id="params-files", classes="open")
        self.query_one("#params").mount(tree, before="#params-status")
        tree.focus()
        self.say("pick a parameter file (.csv, .yaml, .json): arrows, Enter · Esc close")

    def _diff(self, path: Path) -> None:
        try:
            wanted = files.read(path)
        except Abh3Error as exc:
            self.say(str(exc))
            return
        grid = self.query_one(DataTable)
        differ = unknown = 0
        for v in wanted:
            if v.address not in self.words:
                unknown += 1
                continue
            same = self.words[v.address] == v.word
            differ += not same
            grid.update_cell(str(v.address), "file", "" if same else v.shown)
        note = f", {unknown} not read" if unknown else ""
        self.say(f"{differ} parameter(s) differ from {path}{note} (file column)")
