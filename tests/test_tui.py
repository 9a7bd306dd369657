"""The TUI: pilot tests for behaviour on the real runtime over its control socket,
snapshots for layout.

Snapshots render a supervisor run for exactly one second of fake time (the Rig), so
every figure on screen is deterministic. Set ``ABH3_UPDATE_SNAPSHOTS=1`` to rewrite them.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import pty
import re
import select
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from textual import events
from textual.widgets import RichLog, Static

from abh3_supervisor.clients.tui import operator, overview, plots
from abh3_supervisor.clients.tui.app import SupervisorApp
from abh3_supervisor.clients.tui.model import Trace, bus_fields, overview_row
from abh3_supervisor.clients.tui.run import warnings
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.kinematics import twist_to_yx
from abh3_supervisor.core.planner import plan
from abh3_supervisor.plugin_host.hookspecs import hookimpl
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.scheduler.core import HealthEvent
from abh3_supervisor.service.snapshot import supervisor_state
from tests.support.rig import TWO_UNITS, Rig, present, set_velocity
from tests.support.safe_word import assert_demo_stopped
from tests.support.terminal import ended, in_a_terminal
from tests.support.tui import (
    KEYBOARD,
    mirror_of,
    press_until,
    response,
    run_app,
    snapshot_rig,
    twists_applied,
    until,
)

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

SNAPSHOTS = Path(__file__).parent / "snapshots"


def test_estop_from_every_screen_stops_both_units() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        for unit in ("left", "right"):
            assert await sup.command(unit, "SERVO ON ON") == ""
            assert await sup.command(unit, "START ON ON") == ""
        set_velocity(sup, "left", 100, 0, source=present(sup, "left"))
        await pilot.press("2")  # the unit screen: e-stop works from here too
        await pilot.press("ctrl+e")
        await until(pilot, lambda: sup.estop, "the e-stop reaches the service")
        for state in sup.units.values():
            assert (state.setpoint.ay, state.setpoint.bx) == (0, 0)
            assert not state.inputs & state.layout.start.both
        app.refresh_view()
        assert app.query_one("#estop").has_class("latched")
        await pilot.press("E")  # clearing asks first
        await pilot.pause()
        assert sup.estop and isinstance(app.screen, ConfirmScreen)
        await pilot.press("y")
        await until(pilot, lambda: not sup.estop, "the e-stop cleared")

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
        driven = twists_applied(sup)
        await press("n", "up")  # select right, drive forward: refused, saying why and how
        for _ in range(100):  # the service's answer comes through the loop
            if response(app).startswith("refused"):
                break
            await pilot.pause()
        assert response(app) == (
            "refused: robot 'right' may not move: right: SERVO A, SERVO B, START A, START B "
            "not switched on (v to switch SERVO on, s to switch START on)"
        )
        assert not any(d[1] for d in driven)  # the robot decision refused it at the entry
        await press("v", "y", "s", "y", "up")  # switched on: the arrow drives it
        for _ in range(100):  # the feed hands the twist over through the loop
            if driven:
                break
            await pilot.pause()
        # (the setpoint itself may already be back at zero on a slow machine: a tap drives
        # 0.8 s, then the TUI sends zero, which is the point of it)
        name, linear_x, angular_z = next(d for d in driven if d[1])
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
        await until(pilot, lambda: app.sup.units["right"].online is False, "offline on screen")
        app.refresh_view()
        row = overview_row(app.sup, "right")
        assert row["state"] == "OFFLINE"
        shown = str(app.query_one("#table", Static).render())
        (line,) = [x for x in shown.splitlines() if x.startswith("▶ right")]
        # what it said before is not shown as if it held: switches unknown, no feedback
        assert re.match(r"▶ right +OFFLINE \?/\? +\?/\? ", line), line
        assert row["fbk"].split() == ["A", "–", "B", "–"] and row["fbk"] in line
        assert re.search(r"no answer for [\d.]+ s; its last feedback: A [-\d.]+ B", shown)
        await pilot.press("v")  # a key that cannot act says so at once and asks nothing
        await pilot.pause()
        assert not isinstance(app.screen, ConfirmScreen)
        assert "right is OFFLINE" in response(app)
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


@pytest.mark.parametrize("size", [(100, 30), (160, 45)], ids=["100x30", "160x45"])
@pytest.mark.parametrize(
    "keys", [[], ["2"], ["5"], ["question_mark"]], ids=["overview", "unit", "plots", "help"]
)
def test_layout_snapshots(
    keys: list[str], size: tuple[int, int], request: pytest.FixtureRequest
) -> None:
    rig = snapshot_rig()
    mirror = mirror_of(rig)

    async def scenario() -> str:
        app = SupervisorApp(mirror, None)
        for step in range(60):  # 30 s, sampled as the app does
            if step == 30:
                set_velocity(rig.sup, "left", -150, 0, source=present(rig.sup, "left"))
            rig.run(0.5)
            mirror.apply(supervisor_state(rig.sup, {}))
            app.sampler.sample()
        async with app.run_test(size=size) as pilot:
            await pilot.press(*keys)
            await pilot.pause()
            app.refresh_view()
            await pilot.pause()
            return app.export_screenshot()

    snapshot(f"tui-{request.node.callspec.id}", asyncio.run(scenario()))


def test_the_overview_never_splits_a_field_at_any_width() -> None:
    mirror = mirror_of(snapshot_rig())
    for width in (60, 98, 120, 158, 200):
        lines = overview.render(mirror, ["left", "right"], 0, width).plain.splitlines()
        table = [line for line in lines if not line.startswith("    ")][:3]  # header + units
        assert all(len(line) <= width for line in table), (width, table)
        assert "✖ A_OVERCURRENT" in "\n".join(lines) and "▲ CONTROL_UNDERVOLTAGE" in "\n".join(
            lines
        )
    # tripped: the drive dropped its servo, so this supervisor forgot it (no restart)
    assert overview_row(mirror, "right")["servo"] == "off/off"


def test_plots_draw_from_zero_with_value_and_scale() -> None:
    assert plots.bars([300.0, 300.0], 0.0, 300.0, 2) == ["██", "██"]  # steady: a full bar
    assert plots.bars([-150.0], -150.0, 0.0, 2) == ["█", "█"]  # negative: hangs from zero
    assert plots.bars([None, 0.0], 0.0, 1.0, 1) == ["  "]
    rig = snapshot_rig()
    trace = Trace()
    for i in range(10):
        trace.add(float(i), "fbk AY", 100.0 * i)
    text = plots.render(mirror_of(rig).units["left"], trace, 9.0, 80, 3).plain
    assert "fbk Y [min⁻¹]" in text and "now 900.0" in text and "0.0 … 900.0" in text


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_the_tui_in_a_terminal_stops_the_drives_on_a_signal(tmp_path: Path, sig: int) -> None:
    """`abh3 run` on a (pseudo-)terminal opens the TUI; a signal still stops the drives."""
    record = tmp_path / "tui.log"
    pid, fd = in_a_terminal(["run", "configs/demo.yaml", "--record", str(record)])
    os.kill(pid, sig)
    assert ended(pid, fd).code == 0
    assert_demo_stopped(record)


def test_ctrl_c_in_a_terminal_asks_and_yes_stops_the_drives(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The byte a terminal sends for Ctrl-C (the TUI's raw mode makes it no SIGINT): the
    quit question, and yes stops both drives as `q` does."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))  # its own socket
    record = tmp_path / "tui.log"
    pid, fd = in_a_terminal(["run", "configs/demo.yaml", "--record", str(record)])
    os.write(fd, b"\x03")
    screen = b""
    while b"Quit?" not in screen:
        ready, _, _ = select.select([fd], [], [], 30)
        assert ready, f"no question: {screen[-500:]!r}"
        screen += os.read(fd, 65536)
    os.write(fd, b"y")
    assert ended(pid, fd).code == 0
    assert_demo_stopped(record)


class StartLogger:
    @hookimpl
    def abh3_start(self) -> None:
        logging.getLogger("my_plugin").warning("commands from the network ALLOWED")


def test_what_the_service_logs_reaches_the_log_pane() -> None:
    """Before the socket served (the child's log file: its warnings) and after (forwarded
    as events)."""
    child_log = [
        "07:38:11.896 INFO    unit left: startup 'SERVO ON ON' → ''",
        "07:38:11.896 WARNING commands from the network ALLOWED",
        "Traceback-free line without a level",
    ]
    assert warnings(child_log) == [
        (logging.WARNING, "commands from the network ALLOWED"),
        (logging.WARNING, "Traceback-free line without a level"),
    ]

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        logging.getLogger("my_plugin").warning("the network went away")
        await until(
            pilot,
            lambda: any("the network went away" in line.plain for line in app.pending_log),
            "the warning forwarded",
        )
        line = next(x for x in app.pending_log if "the network went away" in x.plain)
        assert str(line.style) == "yellow"

    run_app(check)


def test_every_e_stop_wins_with_the_keyboard_plugin_configured() -> None:
    """The keyboard plugin never reads the terminal the TUI owns: the TUI hands it its
    keys, so 100 e-stops in a row among teleop keys are 100 e-stops."""

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        assert "keyboard" in app.plugin_keys
        keys = app.plugin_keys["keyboard"]
        assert "q" not in keys and "e" not in keys  # the TUI's quit and e-stop win
        assert keys["Q"] == "all speeds ×1.1" and keys["C"] == "angular speed ×1.1"
        stops: list[object] = []
        sup.subscribe(
            lambda e: stops.append(e) if "EMERGENCY" in getattr(e, "message", "") else None
        )
        assert rt.plugins is not None
        plugin = next(s for s in rt.plugins.sources if s.name == "keyboard")
        handed: list[str] = []
        real_press = plugin.press  # type: ignore[attr-defined]

        def press(key: str) -> None:
            handed.append(key)
            real_press(key)

        plugin.press = press  # type: ignore[attr-defined]
        honoured = 0
        for i in range(100):  # each key handled by the service before the next is typed
            for key in ("i", "ctrl+e" if i % 2 else "e", "l"):
                seen = (len(handed), len(stops))
                await press_until(
                    app, pilot, key, lambda s=seen: (len(handed), len(stops)) != s, f"{i}: {key}"
                )
            honoured += sup.estop
            sup.clear_emergency_stop()
        assert honoured == 100 and len(stops) == 100
        assert handed == ["i", "l"] * 100  # every teleop key reached the plugin, none else
        driven = twists_applied(sup)
        # a teleop key, handed to the plugin
        await press_until(app, pilot, "i", lambda: driven, "the keyboard plugin drives")
        assert driven[0][0] == "left" and driven[0][1] == pytest.approx(0.2)

    run_app(check, KEYBOARD, own_terminal=True)


def test_servo_after_an_error_reset_acts_on_what_the_drive_reports() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        left = sup.units["left"]
        lay = left.layout

        def reported_servo() -> bool:
            return bool(left.words.get("control", 0) & lay.servo.both)

        for text in ("SERVO ON ON", "START ON ON", "VEL 120 0"):
            assert await sup.command("left", text, source=present(sup, "left")) == ""
        await until(pilot, reported_servo, "servo on")
        # an error reset from the command line: the drive holds the servo off
        for text in ("RESET ON ON", "RESET OFF OFF"):
            app.run_command(text)
            await app.workers.wait_for_complete()
        await until(pilot, lambda: not reported_servo(), "servo held off after the reset")
        await until(
            pilot, lambda: not app.sup.units["left"].words.get("control", 0) & 1, "shown off"
        )
        # no automatic restart: the drive dropped the servo this supervisor commanded, so
        # SERVO, START and the setpoint are forgotten; the screen shows what is commanded
        await until(pilot, lambda: not app.sup.units["left"].inputs & lay.servo.both, "forgot")
        assert not left.inputs & (lay.servo.both | lay.start.both) and left.setpoint.ay == 0
        app.refresh_view()
        assert overview_row(app.sup, "left")["servo"] == "off/off"  # no '!': nothing held on
        await pilot.press("v")  # off: switching on asks, and nothing would move
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen)
        question = app.screen.question
        assert question.endswith("Send SERVO ON ON?") and "WILL MOVE" not in question
        await pilot.press("y")
        await app.workers.wait_for_complete()
        await until(pilot, reported_servo, "servo on again")
        # `r` switches SERVO off with the reset, so what is shown is what is commanded
        await pilot.press("r")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen) and "SERVO OFF" in app.screen.question
        await pilot.press("y")
        await app.workers.wait_for_complete()
        assert not left.inputs & lay.servo.both
        await until(pilot, lambda: not reported_servo(), "servo off after r")
        # the TUI acts on what it was told: the reset alone turns the reported servo off,
        # so a push from between the reset and SERVO OFF shows it off but still commanded on
        await until(
            pilot,
            lambda: (
                not app.sup.units["left"].words.get("control", 0) & 1
                and not app.sup.units["left"].inputs & lay.servo.both
            ),
            "shown off and commanded off",
        )
        await pilot.press("v")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen)
        assert app.screen.question.endswith("Send SERVO ON ON?")
        await pilot.press("y")
        await app.workers.wait_for_complete()
        await until(pilot, reported_servo, "servo on after v")
        await until(  # again: the TUI acts on the state pushed to it, not on the drive
            pilot, lambda: app.sup.units["left"].words.get("control", 0) & 1, "shown on"
        )
        await pilot.press("v")  # shown on: off at once, nothing asked
        await pilot.pause()
        assert not isinstance(app.screen, ConfirmScreen)
        await app.workers.wait_for_complete()
        assert not left.inputs & lay.servo.both

    run_app(check)


def test_keys_that_cannot_act_say_so_and_ask_nothing() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await pilot.press("ctrl+e")
        await until(pilot, lambda: app.sup.estop, "the e-stop confirmed")
        for key in ("up", "s"):
            await pilot.press(key)
            await pilot.pause()
            assert not isinstance(app.screen, ConfirmScreen)
            assert response(app).startswith("EMERGENCY STOP latched"), key

    run_app(check)
    rig = Rig(
        parse_config(
            TWO_UNITS.replace("velocity_model: motor,", "velocity_model: motor, role: monitor,"),
            "t.yaml",
        )
    )
    for what in operator.SWITCHES:
        step = operator.toggle(mirror_of(rig), "right", what)
        assert not step.commands and "monitor unit" in step.say


def test_speed_keys_stop_at_the_units_limit() -> None:
    rig = Rig(
        parse_config(
            TWO_UNITS.replace("{name: left,", "{name: left, limits: {velocity: 3000},"), "t.yaml"
        )
    )
    speed, turn = operator.speed_caps(mirror_of(rig), ("left",))
    geometry = rig.config.units["left"].geometry
    assert twist_to_yx(speed, 0, geometry)[0] == pytest.approx(3000)
    assert abs(twist_to_yx(0, turn, geometry)[1]) == pytest.approx(3000)

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        cap, _ = operator.speed_caps(app.sup, ("left",))
        for _ in range(40):  # as fast as a held key repeats
            app.post_message(events.Key("plus", "+"))
        await until(pilot, lambda: app.speed == pytest.approx(cap), "the speed capped")
        assert "capped" in response(app)

    run_app(check, TWO_UNITS.replace("{name: left,", "{name: left, limits: {velocity: 3000},"))


def test_operator_actions_and_state_changes_are_in_the_event_log() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await pilot.press("colon", *"SERVO ON ON", "enter")
        await app.workers.wait_for_complete()
        await until(pilot, lambda: rt.supervisor.units["left"].words.get("control", 0) & 1, "servo")
        await pilot.press("s", "n")  # START on? no
        await pilot.press("ctrl+e", "E", "y")
        await pilot.press("4")  # the log tab: the log lays its lines out once shown
        await pilot.pause(0.1)
        lines = [line.text for line in app.query_one("#log-scroll", RichLog).lines]
        text = "\n".join(lines)
        assert re.search(r"^\d\d:\d\d:\d\d unit left: online$", text, re.M)  # online at start
        for wanted in (
            "operator (tui1) on left: :'SERVO ON ON' → ''",
            "operator (tui1) on left: key s: START ON on left:",
            "→ no",
            "operator (tui1): key e-stop: EMERGENCY STOP",
            "operator (tui1): clear the emergency stop? yes",
            "unit left: drive reports +AY_SERVO_ON",
        ):
            assert wanted in text, wanted

    run_app(check)


def test_help_lists_every_binding_by_its_readable_key_and_palette_quit_asks() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await pilot.press("question_mark")
        await pilot.pause()
        help_text = "\n".join(app.screen.lines)  # type: ignore[attr-defined]
        for raw in ("question_mark", "equals_sign", "plus,", "colon"):
            assert raw not in help_text
        assert "  ?" in help_text and "  +, =" in help_text and "Esc" in help_text
        assert "  ctrl+e, e" in help_text and help_text.count("EMERGENCY STOP") == 1
        assert "Plugin keyboard" in help_text and "  Q " in help_text
        assert "  q, ctrl+q, ctrl+c " in help_text
        await pilot.press("escape")
        await app.action_quit()  # what the palette's Quit and ctrl+q run
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen) and "Quit?" in app.screen.question
        await pilot.press("n")
        await pilot.pause()
        assert app.is_running and not isinstance(app.screen, ConfirmScreen)
        await pilot.press("ctrl+q")  # the key itself, as the help lists it: asks once
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen) and "Quit?" in app.screen.question
        await pilot.press("n")
        await pilot.pause()
        assert app.is_running and not isinstance(app.screen, ConfirmScreen)

    run_app(check, KEYBOARD, own_terminal=True)


def test_run_falls_back_to_headless_when_stderr_is_not_a_terminal(tmp_path: Path) -> None:
    """The TUI would draw on stderr: with it in a file, the run is headless, says so in
    one line, and the file holds no escape codes."""
    root = Path(__file__).resolve().parent.parent
    master, slave = pty.openpty()
    err = tmp_path / "err.txt"
    with err.open("w") as stderr:
        code = subprocess.run(
            [
                sys.executable,
                "-m",
                "abh3_supervisor",
                "run",
                "configs/demo.yaml",
                "--duration",
                "1",
            ],
            stdin=slave,
            stdout=slave,
            stderr=stderr,
            cwd=root,
            timeout=60,
        ).returncode
    os.close(slave)
    os.close(master)
    text = err.read_text()
    assert code == 0
    assert text.splitlines()[0] == "abh3: stderr not a terminal: running headless (--headless)"
    assert "\x1b[" not in text and "unit left: online" in text


def test_the_bus_tab_says_what_the_interface_reports() -> None:
    rig = snapshot_rig()
    plans = {p.bus: p for p in plan(rig.config)}
    assert "interface ok" in bus_fields(mirror_of(rig), plans, {})[0]
    rig.sup.bus_health["b"].on_send_error(errno.ENETDOWN, "Network is down", rig.timeline.now)
    assert "interface bus-off" in bus_fields(mirror_of(rig), plans, {})[0]


def test_the_unit_tab_shows_the_drives_firmware_version() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await pilot.press("2")
        head = app.query_one("#unit-head", Static)
        await until(pilot, lambda: "firmware 2.3.0.1" in str(head.render()), "firmware shown")

    run_app(check)


def test_the_title_bar_says_when_the_view_gives_way_to_late_buses() -> None:
    """The pushed state's ``slowed`` (service/view_pace.py) shows in the title bar while
    it lasts, and goes with it; meanwhile a state is stale only once its push is late."""
    rig = snapshot_rig()
    mirror = mirror_of(rig)

    async def scenario() -> list[tuple[str, float]]:
        app = SupervisorApp(mirror, None)
        seen = []
        async with app.run_test(size=(160, 45)) as pilot:
            for by in (None, 4, 16, None):
                rig.run(0.1)
                slowed = None if by is None else {"by": by, "late_ms": 37.2, "quota": by == 16}
                mirror.apply({**supervisor_state(rig.sup, {}), "slowed": slowed})
                app.refresh_view()
                await pilot.pause()
                seen.append((app.sub_title, app.stale_after()))
        return seen

    before, by4, by16, after = asyncio.run(scenario())
    assert "view" not in before[0] and "view" not in after[0]
    assert by4[0].startswith("view 1/4 rate (bus 37.2 ms late) · unit ")
    assert by16[0].startswith("view 1/16 rate (CPU quota reached) · unit ")
    # not stale between pushes that come less often: stale once one is half a second late
    assert (before[1], by4[1], by16[1], after[1]) == pytest.approx((0.5, 0.9, 1.5, 0.5))
