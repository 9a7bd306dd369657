"""The TUI's parameter page (key P) on the real runtime: read all, edit one, diff."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from textual.widgets import DataTable, Static

from abh3_supervisor.clients.tui.app import SupervisorApp, TuiSource
from abh3_supervisor.clients.tui.params import ParamScreen
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.supervisor import OperatorAction
from abh3_supervisor.plugin_host.host import PluginHost
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.conftest import TWO_UNITS


async def until(pilot: Any, condition: Any, what: str) -> None:
    for _ in range(500):  # frames on the virtual bus take real time; bounded
        if condition():
            return
        await pilot.pause(0.01)
    raise AssertionError(f"never: {what}")


def test_read_all_edit_one_with_confirmation_and_diff(tmp_path: Path) -> None:
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    source = TuiSource(tuple(cfg.units))
    host.add_source(source)
    actions: list[str] = []
    saved = tmp_path / "want.yaml"
    saved.write_text(
        "parameters:\n  - {address: '0x5001', value: 450}\n  - {address: '0x5000', value: 800}\n"
    )

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host) as rt:
            sup = rt.supervisor
            sup.subscribe(
                lambda e: actions.append(e.action) if isinstance(e, OperatorAction) else None
            )
            assert await sup.wait_exchange("left", sup.clock(), 2)
            app = SupervisorApp(rt, source)
            async with app.run_test(size=(140, 45)) as pilot:
                await pilot.press("P")
                screen = app.screen
                assert isinstance(screen, ParamScreen)
                status = screen.query_one("#params-status", Static)
                await until(
                    pilot, lambda: "121 parameters read" in str(status.render()), "all read"
                )
                assert "firmware 2.3.0.1" in str(screen.query_one("#params-head", Static).render())
                grid = screen.query_one(DataTable)
                assert grid.get_cell("20480", "value") == "800"  # SPEED_AY_0
                grid.move_cursor(row=grid.get_row_index("20480"))
                await pilot.press("e")
                for ch in "900":
                    await pilot.press(ch)
                await pilot.press("enter")
                assert isinstance(app.screen, ConfirmScreen)
                assert app.screen.question == "Write left 0x5000 SPEED_AY_0: 800 → 900?"
                await pilot.press("y")
                await until(pilot, lambda: "written" in str(status.render()), "written")
                assert grid.get_cell("20480", "value") == "900"
                assert rt.sims["b"].drives[1].tel.params[0x5000] == 0x00400009
                assert actions == ["parameter 0x5000 SPEED_AY_0: 800 (00400008) → 900 (00400009)"]
                await pilot.press("f")
                for ch in str(saved):
                    await pilot.press(ch)
                await pilot.press("enter")
                assert "2 parameter(s) differ" in str(status.render())
                assert grid.get_cell("20481", "file") == "450"  # the drive has 400
                assert grid.get_cell("20480", "file") == "800"  # the drive has 900 now
                await pilot.press("escape")
                assert not isinstance(app.screen, ParamScreen)

    asyncio.run(scenario())
