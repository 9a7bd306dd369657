"""The TUI's parameter page (key P) over the socket of a real runtime: read all, edit one,\ndiff."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from textual.widgets import DataTable, Input, Static

from abh3_supervisor.clients.tui.app import SupervisorApp
from abh3_supervisor.clients.tui.params import ParamScreen
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from abh3_supervisor.core.supervisor import OperatorAction
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.test_tui import run_app, until


def test_read_all_edit_one_with_confirmation_and_diff(tmp_path: Path) -> None:
    saved = tmp_path / "want.yaml"
    saved.write_text(
        "parameters:\n  - {address: '0x5001', value: 450}\n  - {address: '0x5000', value: 800}\n"
    )

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
        grid.move_cursor(row=grid.get_row_index("20480"))
        await pilot.press("e")
        screen.query_one("#params-input", Input).value = "900"  # as typed
        await pilot.press("enter")
        assert isinstance(app.screen, ConfirmScreen)
        assert app.screen.question == "Write left 0x5000 SPEED_AY_0: 800 → 900?"
        await pilot.press("y")
        await until(pilot, lambda: "written" in str(status.render()), "written")
        assert grid.get_cell("20480", "value") == "900"
        assert rt.sims["b"].drives[1].tel.params[0x5000] == 0x00400009
        assert actions == ["parameter 0x5000 SPEED_AY_0: 800 (00400008) → 900 (00400009)"]
        await pilot.press("f")
        screen.query_one("#params-input", Input).value = str(saved)
        await pilot.press("enter")
        assert "2 parameter(s) differ" in str(status.render())
        assert grid.get_cell("20481", "file") == "450"  # the drive has 400
        assert grid.get_cell("20480", "file") == "800"  # the drive has 900 now
        await pilot.press("escape")
        assert not isinstance(app.screen, ParamScreen)

    run_app(check, size=(140, 45))
