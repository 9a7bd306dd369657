"""The TUI's parameter page (key P) over the socket of a real runtime: read all, write one,
diff against a file picked (not typed: a path may hold an `e`, the e-stop)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from textual.widgets import DataTable, Input, Static

from abh3_supervisor.clients.tui.app import SupervisorApp
from abh3_supervisor.clients.tui.params import ParameterFiles, ParamScreen
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from abh3_supervisor.core.supervisor import OperatorAction
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.support.tui import run_app, until

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes


def test_read_all_write_one_with_confirmation_and_diff(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    saved = tmp_path / "want.yaml"
    saved.write_text(
        "parameters:\n  - {address: '0x5001', value: 450}\n  - {address: '0x5000', value: 800}\n"
    )
    (tmp_path / "notes.txt").write_text("not a parameter file")
    monkeypatch.chdir(tmp_path)  # the picker shows the directory the TUI started in

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        actions: list[str] = []
        rt.supervisor.subscribe(
            lambda e: actions.append(e.action) if isinstance(e, OperatorAction) else None
        )
        await pilot.press("P")
        screen = app.screen
        assert isinstance(screen, ParamScreen)
        status = screen.query_one("#params-status", Static)
        await until(pilot, lambda: "121 parameters read" in str(status.render()), "all read")
        assert "firmware 2.3.0.1" in str(screen.query_one("#params-head", Static).render())
        grid = screen.query_one(DataTable)
        assert grid.get_cell("20480", "value") == "800"  # SPEED_AY_0
        from textual.widgets.data_table import ColumnKey

        assert grid.columns[ColumnKey("word")].content_width >= 8  # all of it, not 0040
        grid.move_cursor(row=grid.get_row_index("20480"))
        await pilot.press("w")
        screen.query_one("#params-input", Input).value = "900"  # as typed
        assert await rt.supervisor.command("left", "SERVO ON ON") == ""  # the drive has it
        await pilot.press("enter")  # the drive is asked first: on, so no question at all
        await until(pilot, lambda: "servo ON (asked now)" in str(status.render()), "refused")
        assert not isinstance(app.screen, ConfirmScreen)
        assert await rt.supervisor.command("left", "SERVO OFF OFF") == ""
        await pilot.press("w")
        screen.query_one("#params-input", Input).value = "900"
        await pilot.press("enter")
        await until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "asked")
        assert isinstance(app.screen, ConfirmScreen)
        assert app.screen.question == "Write left 0x5000 SPEED_AY_0: 800 → 900?"
        await pilot.press("y")
        await until(pilot, lambda: "written" in str(status.render()), "written")
        assert grid.get_cell("20480", "value") == "900"
        assert rt.sims["b"].drives[1].tel.params[0x5000] == 0x00400009
        assert actions == ["parameter 0x5000 SPEED_AY_0: 800 (00400008) → 900 (00400009)"]
        await pilot.press("f")
        tree = screen.query_one(ParameterFiles)
        await until(pilot, lambda: len(tree.root.children) == 1, "the files listed")
        assert str(tree.root.children[0].label) == "want.yaml"  # parameter files only
        tree.move_cursor(tree.root.children[0])
        await pilot.press("enter")
        await until(pilot, lambda: "differ" in str(status.render()), "compared")
        assert "2 parameter(s) differ" in str(status.render())
        assert grid.get_cell("20481", "file") == "450"  # the drive has 400
        assert grid.get_cell("20480", "file") == "800"  # the drive has 900 now
        await pilot.press("enter")  # Enter on a row writes it too
        assert screen.query_one("#params-input", Input).has_class("open")
        await pilot.press("escape", "escape")  # the input line, then the page
        assert not isinstance(app.screen, ParamScreen)

    run_app(check, size=(140, 45))
