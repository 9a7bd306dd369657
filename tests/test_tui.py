"""The TUI: pilot tests for behaviour on the real runtime, snapshots for layout.

Snapshots render a supervisor run for exactly one second of fake time (the Rig), so
every figure on screen is deterministic. Set ``ABH3_UPDATE_SNAPSHOTS=1`` to rewrite them.
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import pty
import re
import select
import signal
import struct
import sys
import termios
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from textual.widgets import Static

from abh3_supervisor.config import parse_config
from abh3_supervisor.hookspecs import hookimpl
from abh3_supervisor.plugin_host import PluginHost
from abh3_supervisor.protocol import flags
from abh3_supervisor.runtime import Runtime
from abh3_supervisor.runtime_thread import RuntimeThread
from abh3_supervisor.scheduler.core import HealthEvent
from abh3_supervisor.supervisor import SetResult
from abh3_supervisor.tui.app import SupervisorApp, TuiSource, start_logged
from abh3_supervisor.tui.screens import ConfirmScreen
from tests.conftest import TWO_UNITS, Rig

SNAPSHOTS = Path(__file__).parent / "snapshots"


def run_app(check: Any) -> None:
    """Run the app on the real runtime (virtual bus, simulated drives) and a pilot."""
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    source = TuiSource(tuple(cfg.units))
    host.add_source(source)

    async def scenario() -> None:
        async with Runtime(cfg, plugins=host) as rt:
            sup = rt.supervisor
            since = sup.clock()
            assert all(await asyncio.gather(*(sup.wait_exchange(n, since, 2) for n in sup.units)))
            app = SupervisorApp(rt, source)
            async with app.run_test(size=(180, 40)) as pilot:
                await check(app, pilot, rt)

    asyncio.run(scenario())


def response(app: SupervisorApp) -> str:
    return str(app.query_one("#response").render())


def test_estop_from_every_screen_stops_both_units() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        for unit in ("left", "right"):
            assert await sup.command(unit, "SERVO ON ON") == ""
            assert await sup.command(unit, "START ON ON") == ""
        sup.set_velocity("left", 100, 0)
        await pilot.press("2")  # the unit screen: e-stop works from here too
        await pilot.press("ctrl+e")
        assert sup.estop
        for state in sup.units.values():
            assert (state.setpoint.ay, state.setpoint.bx) == (0, 0)
            assert not state.inputs & state.layout.start.both
        app.refresh_view()
        assert app.query_one("#estop").has_class("latched")
        await pilot.press("E")  # clearing asks first
        await pilot.pause()
        assert sup.estop and isinstance(app.screen, ConfirmScreen)
        await pilot.press("y")
        await pilot.pause()
        assert not sup.estop

    run_app(check)


def test_command_line_answers_exactly_as_the_seed() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await pilot.press("colon", *"SERVO ON ON", "enter")
        await app.workers.wait_for_complete()
        assert response(app) == "left ← 'SERVO ON ON' → ''"
        await pilot.press("colon", *"FOO", "enter")
        await app.workers.wait_for_complete()
        assert response(app) == "left ← 'FOO' → 'Invalid Command.'"
        for text in ("SELECT ² 7", "VEL ١٠ 0", "SERVO\x00 ON ON"):  # once crashed the TUI
            app.run_command(text)  # a worker, as the command line starts it
            await app.workers.wait_for_complete()
            assert response(app) == f"left ← {text!r} → 'Invalid Command.'"

    run_app(check)


def test_risky_toggles_ask_first_and_arrows_drive_the_selected_unit() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor

        async def press(*keys: str) -> None:
            for key in keys:
                await pilot.press(key)
                await pilot.pause()
            await app.workers.wait_for_complete()

        await press("v", "n")  # servo on? no
        left = sup.units["left"].layout
        assert not sup.units["left"].inputs & left.servo.both
        await press("v", "y", "s", "y")
        assert sup.units["left"].inputs & left.start.both
        assert not isinstance(app.screen, ConfirmScreen)
        await press("d", "y")  # data select: written 7 → 6 (set #1) on both axes
        assert left.data_select(sup.units["left"].inputs) == (6, 6)
        driven: list[tuple[str, float, float]] = []
        real = sup.set_twist

        def spy(name: str, linear_x: float, angular_z: float) -> SetResult:
            driven.append((name, linear_x, angular_z))
            return real(name, linear_x, angular_z)

        sup.set_twist = spy  # type: ignore[method-assign]
        await press("n", "up")  # select right, drive forward
        assert response(app).startswith("drive right")
        for _ in range(100):  # the feed hands the twist over through the loop
            if driven:
                break
            await pilot.pause()
        # (the setpoint itself may already be back at zero on a slow machine: the TUI's
        # source goes stale 0.6 s after the key, which is the point of it)
        name, linear_x, angular_z = driven[0]
        assert (name, angular_z) == ("right", 0.0) and linear_x == pytest.approx(0.2)

    run_app(check)


def test_a_silenced_unit_turns_offline_on_screen() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        gone = asyncio.get_running_loop().create_future()

        def watch(event: object) -> None:
            if isinstance(event, HealthEvent) and not event.online and not gone.done():
                gone.set_result(event.unit)

        rt.supervisor.subscribe(watch)
        await pilot.press("n", "f")  # silence the simulated right unit
        assert await asyncio.wait_for(gone, 3) == "right"
        app.refresh_view()
        assert app.overview_rows["right"]["state"] == "OFFLINE"
        assert "OFFLINE" in str(app.query_one("#table", Static).render())
        await pilot.press("f")

    run_app(check)


def snapshot(name: str, svg: str) -> None:
    # strip what differs between runs but is not layout: generated ids
    svg = re.sub(r"terminal-\d+", "terminal", svg)
    path = SNAPSHOTS / f"{name}.svg"
    if os.environ.get("ABH3_UPDATE_SNAPSHOTS") or not path.exists():
        SNAPSHOTS.mkdir(exist_ok=True)
        path.write_text(svg, encoding="utf-8")
        if not os.environ.get("ABH3_UPDATE_SNAPSHOTS"):
            pytest.fail(f"new snapshot written: {path}; check it and run again")
    assert svg == path.read_text(encoding="utf-8"), f"{name} layout changed (see {path})"


@pytest.mark.parametrize("keys", [[], ["2"], ["question_mark"]], ids=["overview", "unit", "help"])
def test_layout_snapshots(keys: list[str], request: pytest.FixtureRequest) -> None:
    rig = Rig(parse_config(TWO_UNITS, "t.yaml"))
    rig.sup.apply_text("left", "SERVO ON ON")
    rig.sup.apply_text("left", "START ON ON")
    rig.sup.set_velocity("left", 100, 10)
    rig.run(1.0)
    rt = SimpleNamespace(config=rig.config, supervisor=rig.sup, pumps={}, sims={}, plugins=None)

    async def scenario() -> str:
        app = SupervisorApp(rt, TuiSource(("left", "right")))  # type: ignore[arg-type]
        async with app.run_test(size=(160, 40)) as pilot:
            await pilot.press(*keys)
            await pilot.pause()
            app.refresh_view()
            await pilot.pause()
            return app.export_screenshot()

    snapshot(f"tui-{request.node.callspec.id}", asyncio.run(scenario()))


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_the_tui_in_a_terminal_stops_the_drives_on_a_signal(tmp_path: Path, sig: int) -> None:
    """`abh3 run` on a (pseudo-)terminal opens the TUI; a signal still stops the drives."""
    record = tmp_path / "tui.log"
    root = Path(__file__).resolve().parent.parent
    pid, fd = pty.fork()
    if pid == 0:  # the child: the program, on the terminal
        os.chdir(root)
        os.execv(
            sys.executable,
            [
                sys.executable,
                "-m",
                "abh3_supervisor",
                "run",
                "configs/demo.yaml",
                "--record",
                str(record),
            ],
        )
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 180, 0, 0))
    screen = b""
    while screen.count(b"online") < 2:  # wait until the live table shows both units online
        ready, _, _ = select.select([fd], [], [], 20)
        assert ready, f"no TUI output: {screen[-500:]!r}"
        screen += os.read(fd, 65536)
    os.kill(pid, sig)
    while True:  # drain the terminal until the program has gone
        ready, _, _ = select.select([fd], [], [], 20)
        try:
            if not ready or not os.read(fd, 65536):
                break
        except OSError:
            break
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    import can

    from abh3_supervisor.protocol import frames, ids

    layouts = {1: flags.LAYOUT_2021, 3: flags.LAYOUT_2023}  # as in TWO_UNITS
    last = {}
    for msg in can.LogReader(str(record)):
        for abh3, lay in layouts.items():
            if msg.arbitration_id == ids.dp0_command_id(abh3, 2):
                last[abh3] = frames.decode_dp0_command(bytes(msg.data), lay.generation)
    assert len(last) == 2
    for abh3, cmd in last.items():
        assert isinstance(cmd, frames.Dp0Command) and (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0)
        assert cmd.inputs & ~layouts[abh3].select_mask == 0  # the safe word


class StartLogger:
    @hookimpl
    def abh3_start(self) -> None:
        logging.getLogger("my_plugin").warning("commands from the network ALLOWED")


def test_what_plugins_log_at_start_reaches_the_log_pane() -> None:
    cfg = parse_config(TWO_UNITS, "t.yaml")
    host = PluginHost(cfg)
    host.register(StartLogger(), "start_logger")
    bridge = RuntimeThread(cfg, record=None, plugins=host)
    handlers = list(logging.getLogger().handlers)
    try:
        _, early = start_logged(bridge)
    finally:
        bridge.stop()
    assert [line.plain[9:] for line in early] == ["commands from the network ALLOWED"]
    assert str(early[0].style) == "yellow"
    assert logging.getLogger().handlers == handlers  # the capture ends with the start
