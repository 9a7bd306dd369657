"""The TUI never misleads the operator (issue 21): the e-stop key is never shadowed, no
claim is made without the service, stale values say so, one axis vocabulary, and the
service's clamp notes are shown."""

from __future__ import annotations

import asyncio
import itertools
import re
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from textual import events
from textual.keys import _character_to_key
from textual.screen import ModalScreen
from textual.widgets import Input, Static, TabbedContent

from abh3_supervisor.clients.tui import operator, overview
from abh3_supervisor.clients.tui.app import ESTOP_CONFIRM_S, SupervisorApp
from abh3_supervisor.clients.tui.hold import REPEAT_GAP_S, RESEND_S, TICK_S
from abh3_supervisor.clients.tui.model import detail_fields, overview_row, series_label
from abh3_supervisor.clients.tui.params import ParameterFiles, ParamScreen
from abh3_supervisor.clients.tui.screens import ConfirmScreen, HelpScreen
from abh3_supervisor.core.supervisor import Notice
from abh3_supervisor.params import table
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.server import CLIENT_TIMEOUT_S, ControlServer
from abh3_supervisor.service.snapshot import supervisor_state
from tests.support.tui import (
    KEYBOARD,
    mirror_of,
    press_until,
    response,
    run_app,
    snapshot_rig,
    until,
)

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

Check = Callable[[SupervisorApp], bool]
Step = tuple[str, Check] | Callable[[SupervisorApp, Any], Awaitable[None]]
SERVERS: list[ControlServer] = []


@pytest.fixture(autouse=True)
def remember_servers(monkeypatch: pytest.MonkeyPatch) -> None:
    """The server run_app starts, for the tests that act on the service's side."""
    SERVERS.clear()
    real = ControlServer.start

    async def start(self: ControlServer) -> None:
        SERVERS.append(self)
        await real(self)

    monkeypatch.setattr(ControlServer, "start", start)


async def first_parameter_read(app: SupervisorApp, pilot: Any) -> None:
    screen = app.screen
    assert isinstance(screen, ParamScreen)
    first = table.PARAMETERS[0].address  # the row under the cursor
    await until(pilot, lambda: first in screen.words, "the first parameter read")


async def latched_elsewhere(app: SupervisorApp, pilot: Any) -> None:
    SERVERS[0].rt.supervisor.emergency_stop()  # another client's: E asks to clear it
    await until(pilot, lambda: app.sup.estop, "the e-stop shown")


def on(kind: type) -> Check:
    return lambda app: isinstance(app.screen, kind)


def typing(kind: type, text: str = "") -> Check:
    return lambda app: isinstance(app.focused, kind) and getattr(app.focused, "value", "") == text


def tab(name: str) -> Check:
    return lambda app: app.query_one(TabbedContent).active == name


async def step(app: SupervisorApp, pilot: Any, what: Step) -> None:
    """A key as the terminal delivers it, until its effect shows (press_until: a pilot's
    press waits for an idle process, which the buses in this one rarely allow)."""
    if callable(what):
        await what(app, pilot)
    else:
        key, done = what
        await press_until(app, pilot, key, lambda: done(app), key)


# every tab, page, question and input line, and how to get there
PLACES: dict[str, tuple[Step, ...]] = {
    "tab overview": (("1", tab("overview")),),
    "tab unit": (("2", tab("unit")),),
    "tab bus": (("3", tab("bus")),),
    "tab log": (("4", tab("log")),),
    "tab plots": (("5", tab("plots")),),
    "help": (("question_mark", on(HelpScreen)),),
    "question: servo on": (("v", on(ConfirmScreen)),),
    "question: data select": (("d", on(ConfirmScreen)),),
    "question: quit": (("q", on(ConfirmScreen)),),
    "question: clear the e-stop": (latched_elsewhere, ("E", on(ConfirmScreen))),
    "command line, typing": (
        ("colon", typing(Input, "SER")),  # what was typed before is kept …
        ("S", typing(Input, "S")),  # … and selected: typing replaces it
        ("E", typing(Input, "SE")),
        ("R", typing(Input, "SER")),
    ),
    "parameter page": (("P", on(ParamScreen)),),
    "parameter value input": (
        ("P", on(ParamScreen)),
        first_parameter_read,
        ("w", typing(Input)),
        ("9", typing(Input, "9")),
    ),
    "parameter write question": (
        ("P", on(ParamScreen)),
        first_parameter_read,
        ("w", typing(Input)),
        ("9", typing(Input, "9")),
        ("enter", on(ConfirmScreen)),
    ),
    "parameter file picker": (("P", on(ParamScreen)), ("f", typing(ParameterFiles))),
}


# the input lines: there `e` is text, and only ctrl+e is the e-stop
TYPING = ("command line, typing", "parameter value input")


async def types_e(app: SupervisorApp, pilot: Any, place: str) -> None:
    """`e` goes into the focused input line as text (and is taken out again)."""
    line = app.focused
    assert isinstance(line, Input), place
    before = line.value
    await press_until(app, pilot, "e", lambda: line.value == before + "e", f"{place}: e typed")
    await press_until(app, pilot, "backspace", lambda: line.value == before, place)


def test_ctrl_e_latches_the_estop_everywhere_and_e_everywhere_but_in_an_input() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        stops: list[Notice] = []
        sup.subscribe(
            lambda e: (
                stops.append(e) if isinstance(e, Notice) and "EMERGENCY" in e.message else None
            )
        )
        app.query_one("#cmdline", Input).value = "SER"
        for place, steps in PLACES.items():
            for key in ("ctrl+e",) if place in TYPING else ("e", "ctrl+e"):
                for what in steps:
                    await step(app, pilot, what)
                seen = len(stops)
                if place in TYPING:
                    await types_e(app, pilot, place)
                    assert not sup.estop and len(stops) == seen, place
                await press_until(app, pilot, key, lambda s=seen: len(stops) > s, place)
                assert sup.estop, (place, key)  # every unit zero, START off, latched
                confirmed = lambda: response(app).startswith("EMERGENCY STOP latched")  # noqa: E731
                await until(pilot, confirmed, f"{place}: {key} confirmed")
                assert app.sup.estop, (place, key)
                # every question and page closed, so the outcome is in sight
                assert not isinstance(app.screen, ModalScreen) and app.focused is None, place
                sup.clear_emergency_stop()
                await until(pilot, lambda: not app.sup.estop, "cleared")
        assert app.query_one("#cmdline", Input).value == "SER"  # nothing else was typed

    run_app(check, size=(140, 45))


def test_ctrl_c_asks_to_quit_from_everywhere_and_sends_nothing_else() -> None:
    """The key a new user presses first: on every tab, page, question and input line it
    closes what is open (a question as no) and asks the quit question — one, however
    often it is pressed; no says so and leaves everything running."""

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        asked: list[str] = []
        real_push = app.push_screen

        def push(screen: Any, *args: Any, **kwargs: Any) -> Any:
            if isinstance(screen, ConfirmScreen):
                asked.append(screen.question)
            return real_push(screen, *args, **kwargs)

        app.push_screen = push  # type: ignore[method-assign]
        app.query_one("#cmdline", Input).value = "SER"
        for place, steps in PLACES.items():
            for what in steps:
                await step(app, pilot, what)
            asked.clear()
            made = recording(app)
            latched = sup.estop  # the place "question: clear the e-stop" latches it first
            await press_until(app, pilot, "ctrl+c", app.quitting, place)
            # the place closed under the question; nothing typed, nothing sent but the audit
            assert app.screen_stack[1:] == [app.screen] and app.focused is not None, place
            assert not isinstance(app.focused, Input), place
            await press_until(app, pilot, "ctrl+c", app.quitting, place)  # again: nothing new
            await press_until(app, pilot, "n", lambda: len(app.screen_stack) == 1, place)
            # one question, the one open already at "question: quit"
            assert asked == ([] if place == "question: quit" else [app.QUIT]), (place, asked)
            assert app.is_running and sup.estop == latched, place
            reads = {"param_read", "param_identity"}  # a page's, in flight as it closes
            assert {method for _, method, _ in made} <= {"audit", *reads}, (place, made)
            if latched:
                sup.clear_emergency_stop()
                await until(pilot, lambda: not app.sup.estop, "cleared")
            app.request = SupervisorApp.request.__get__(app)  # type: ignore[method-assign]
        assert app.query_one("#cmdline", Input).value == "SER"  # nothing else was typed

    run_app(check, size=(140, 45))


def test_ctrl_c_stops_the_arrows_drive_at_once_and_yes_quits() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        for text in ("SERVO ON ON", "START ON ON"):
            assert await sup.command("left", text) == ""
        unit = app.sup.units["left"]
        both = unit.layout.servo.both | unit.layout.start.both
        await until(pilot, lambda: unit.words.get("control", 0) & both == both, "reported on")
        made = recording(app)
        await press_until(app, pilot, "up", lambda: sup.units["left"].setpoint.ay > 0, "up")
        assert app.hold.drive is not None
        await press_until(app, pilot, "ctrl+c", app.quitting, "ctrl+c")
        # zero sent with the question, not after the key's release timeout
        assert app.hold.drive is None
        assert made[-1][1:] == ("twist", {"robots": ["left"], "linear_x": 0.0, "angular_z": 0.0})
        assert "stop sent" in response(app)
        await until(pilot, lambda: sup.units["left"].setpoint.ay == 0, "stopped")
        await press_until(app, pilot, "y", lambda: not app.is_running, "yes: quits")

    run_app(check)


def test_keys_typed_right_after_colon_are_text() -> None:
    """A fast typist (or a paste): `:` then `ser` at once is the text `ser`, not START,
    the e-stop and an error reset; `w` then a value on the parameter page likewise."""

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        cmdline = app.query_one("#cmdline", Input)
        made = recording(app)
        for key in ("colon", "s", "e", "r"):
            app.post_message(events.Key(key, ":" if key == "colon" else key))
        await until(pilot, lambda: cmdline.value == "ser" or sup.estop, "typed")
        assert cmdline.value == "ser" and not sup.estop and made == []
        assert not isinstance(app.screen, ModalScreen)
        await press_until(app, pilot, "escape", lambda: app.focused is None, "Esc")
        for what in PLACES["parameter page"]:
            await step(app, pilot, what)
        await first_parameter_read(app, pilot)
        for key in ("w", "1", "e", "3"):
            app.post_message(events.Key(key, key))
        typed = typing(Input, "1e3")
        await until(pilot, lambda: typed(app) or sup.estop, "the value typed")
        assert typed(app) and not sup.estop
        for _ in range(2):  # the input line, then the page
            app.post_message(events.Key("escape", None))
        await until(pilot, lambda: not isinstance(app.screen, ParamScreen), "page closed")

    run_app(check)


async def type_text(app: SupervisorApp, pilot: Any, text: str) -> None:
    """Each character as the terminal delivers it, into the focused input line."""
    line = app.focused
    assert isinstance(line, Input)
    start = line.value
    for n, ch in enumerate(text, 1):
        app.post_message(events.Key(_character_to_key(ch), ch))
        await until(pilot, lambda n=n: line.value == start + text[:n], f"{ch!r} typed")


def recording(app: SupervisorApp) -> list[tuple[float, str, dict[str, Any]]]:
    """Every request the app makes from now on: (its clock, method, params)."""
    made: list[tuple[float, str, dict[str, Any]]] = []
    real = app.request

    async def request(method: str, **params: Any) -> Any:
        made.append((app.clock(), method, params))
        return await real(method, **params)

    app.request = request  # type: ignore[method-assign]
    return made


def test_every_printable_key_is_text_in_every_input_line() -> None:
    """Every binding of every screen: none takes a printable key from an input line, and
    the up/down arrows do not drive from there."""
    every = "".join(chr(c) for c in range(0x20, 0x7F))

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        cmdline = app.query_one("#cmdline", Input)
        await press_until(app, pilot, "colon", lambda: app.focused is cmdline, ":")
        made = recording(app)
        await type_text(app, pilot, every)
        for key in ("up", "down"):
            app.post_message(events.Key(key, None))
        await type_text(app, pilot, "E")  # handled after the arrows: they did nothing
        assert made == [] and app.hold.drive is None and not rt.supervisor.estop
        assert not isinstance(app.screen, ModalScreen) and app.focused is cmdline
        await press_until(app, pilot, "escape", lambda: app.focused is None, "Esc")
        cmdline.value = ""
        for what in PLACES["parameter value input"]:
            await step(app, pilot, what)
        await type_text(app, pilot, every)
        assert isinstance(app.screen, ParamScreen) and app.screen.mode == "edit"
        assert not rt.supervisor.estop
        for _ in range(2):  # the input line, then the page (its reads end with it)
            app.post_message(events.Key("escape", None))
        await until(pilot, lambda: not isinstance(app.screen, ParamScreen), "page closed")

    run_app(check, KEYBOARD, own_terminal=True)


def test_commands_are_case_insensitive_from_the_command_line() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        left = rt.supervisor.units["left"]
        cmdline = app.query_one("#cmdline", Input)
        for text in ("Servo on on", "start ON on", "vel 50 0"):
            await press_until(app, pilot, "colon", lambda: app.focused is cmdline, ":")
            await type_text(app, pilot, text)
            answer = f"left ← {text!r} → ''"
            await press_until(app, pilot, "enter", lambda a=answer: response(app) == a, text)
        assert left.inputs & left.layout.start.both == left.layout.start.both
        assert (left.setpoint.ay, left.setpoint.bx) == (50, 0)
        await press_until(app, pilot, "colon", lambda: app.focused is cmdline, ":")
        await type_text(app, pilot, "vel 0 0")
        await press_until(app, pilot, "ctrl+e", lambda: rt.supervisor.estop, "ctrl+e")
        assert (left.setpoint.ay, left.setpoint.bx) == (0, 0) and app.focused is None

    run_app(check)


def test_arrows_with_servo_or_start_off_say_why_nothing_moves() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        keys = "(v to switch SERVO on, s to switch START on)"
        said = {  # the service's answer: the robot decision's refusal, with the keys
            "": "refused: robot 'left' may not move: left: SERVO A, SERVO B, START A, "
            f"START B not switched on {keys}",
            "SERVO ON ON": f"refused: robot 'left' may not move: left: START A, START B not "
            f"switched on {keys}",
            "START ON ON": "drive left: +0.20 m/s +0.00 rad/s (hold the key; release = stop)",
        }
        app.clock = lambda: now[0]
        mirror = app.sup.units["left"]  # its words are replaced with every state
        await until(pilot, lambda: "control" in mirror.words, "the control word reported")
        for command, text in said.items():
            if command:
                assert await sup.command("left", command) == ""
                pair = mirror.layout.servo if "SERVO" in command else mirror.layout.start
                on = lambda p=pair: mirror.words["control"] & p.both == p.both  # noqa: E731
                await until(pilot, on, f"{command} reported")
            app.say("")
            await press_until(app, pilot, "up", lambda t=text: response(app) == t, command)
            now[0] += 1.0  # no repeat: the key is up
            app.drive_tick()
            assert app.hold.drive is None
            released = "drive left: key released, stop sent"
            assert response(app) == (released if command == "START ON ON" else text)

    now = [0.0]
    run_app(check)


def test_why_nothing_moves_is_judged_from_what_the_drive_reports() -> None:
    """left runs (SERVO, START on as reported); right tripped (an error: its SERVO off,
    forgotten by the supervisor), START off; a unit not heard from yet is judged by its
    command, and says so."""
    mirror = mirror_of(snapshot_rig())
    assert operator.stillness(mirror, ("left",)) is None
    assert operator.stillness(mirror, ("left", "right")) == (
        "right: SERVO off, START off — nothing moves (v to switch SERVO on, s to switch START on)"
    )
    del mirror.units["left"].words["control"]
    mirror.units["left"].inputs &= ~mirror.units["left"].layout.start.both
    assert operator.stillness(mirror, ("left",)) == (
        "left: START off (as commanded: the drive has not reported yet) — nothing moves "
        "(s to switch START on)"
    )


def test_a_held_arrow_is_kept_fresh_across_the_repeat_delay_and_stops_on_release() -> None:
    """On the app's clock (fake): the press, the terminal's first repeat 0.6 s later, then
    one every 0.033 s: the twist is re-sent well inside the service's freshness, never
    zero in between; once the repeats end, zero within the bound."""
    now, ticks = [0.0], [0]

    async def at(app: SupervisorApp, t: float) -> None:
        while (ticks[0] + 1) * TICK_S <= t:  # the app's interval timer, on the fake clock
            ticks[0] += 1
            now[0] = ticks[0] * TICK_S
            app.drive_tick()
        now[0] = t

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        for text in ("SERVO ON ON", "START ON ON"):
            assert await sup.command("left", text) == ""
        unit = app.sup.units["left"]
        both = unit.layout.servo.both | unit.layout.start.both
        await until(pilot, lambda: unit.words.get("control", 0) & both == both, "reported on")
        app.clock = lambda: now[0]
        sent: list[tuple[float, float]] = []  # when the app sent a twist (its clock), what
        real = app.send

        def send(method: str, **params: Any) -> None:
            if method == "twist":
                sent.append((now[0], params["linear_x"]))
            real(method, **params)

        app.send = send  # type: ignore[method-assign]
        keys = [0.0] + [round(0.6 + i * 0.033, 3) for i in range(20)]
        for t in keys:
            await at(app, t)
            await press_until(app, pilot, "up", lambda t=t: app.hold.key_at == t, f"up at {t}")
            if t == 0.0:
                await until(pilot, lambda: sup.units["left"].setpoint.ay != 0, "driving")
        held = list(sent)
        assert held[0] == (0.0, 0.2) and all(v == 0.2 for _, v in held)  # never zero
        gaps = [b - a for (a, _), (b, _) in itertools.pairwise(held)]
        assert max(gaps) <= RESEND_S + TICK_S < CLIENT_TIMEOUT_S  # always fresh
        await at(app, keys[-1] + REPEAT_GAP_S + TICK_S)  # no more repeats: released
        assert sent[-1][1] == 0.0 and app.hold.drive is None
        assert "key released, stop sent" in response(app)
        await until(pilot, lambda: sup.units["left"].setpoint.ay == 0, "stopped")

    run_app(check)


def test_without_the_service_nothing_is_claimed_and_values_are_stale() -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        for text in ("SERVO ON ON", "START ON ON", "VEL 300 20"):
            assert await sup.command("left", text) == ""
        await until(pilot, lambda: app.sup.units["left"].setpoint.ay == 300, "driven")
        # first the service silent while connected: the screen says so within 0.5 s
        assert app.link is not None
        await app.link.call("subscribe", events=True, state_hz=0)
        table_text = app.query_one("#table", Static)
        await until(pilot, lambda: "STALE" in str(table_text.render()), "stale shown")
        assert app.query_one(TabbedContent).has_class("stale")
        await press_until(app, pilot, "d", lambda: isinstance(app.screen, ConfirmScreen), "d")
        # then gone, a question open: a crash, no "bye"
        for client in list(SERVERS[0].clients):
            client.writer.close()
        await until(pilot, lambda: app.gone is not None, "the loss seen")
        await press_until(app, pilot, "y", lambda: "NOT SENT" in response(app), "yes, too late")
        assert response(app).startswith(
            "left ← SELECT 6 6 → 'NOT SENT — not connected to the supervisor: the "
        )  # … supervisor closed the connection, or … connection broke: how it ended
        await press_until(app, pilot, "e", lambda: "E-STOP" in response(app), "e")
        said = response(app)
        assert said.startswith("E-STOP NOT SENT — not connected")
        assert "hardware emergency stop" in said and "command-zero timeout" in said
        assert not sup.estop and not app.sup.estop  # nothing sent, nothing claimed
        app.refresh_view()
        assert not app.query_one("#estop").has_class("latched")
        for key in ("v", "s", "up", "space", "E", "colon", "P", "f", "r", "d", "i"):
            app.say("")
            refused = lambda: response(app).startswith("NOT SENT — not connected")  # noqa: E731
            await press_until(app, pilot, key, refused, key)
            assert not isinstance(app.screen, ModalScreen), key  # nothing asked either
        rows = str(table_text.render()).splitlines()
        assert re.match(r"STALE: these values are [\d.]+ s old, not live", rows[0])
        unit_rows = [r for r in rows if r.lstrip("▶ ").startswith(("left", "right"))]
        assert len(unit_rows) == 2 and all(" stale " in r and "online" not in r for r in unit_rows)
        await pilot.press("2")
        app.refresh_view()
        assert str(app.query_one("#unit-head", Static).render()).startswith("STALE")

    run_app(check, KEYBOARD, own_terminal=True)


def test_an_estop_the_service_does_not_confirm_is_not_shown_latched(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def late(self: ControlServer, client: Any, params: dict[str, Any]) -> Any:
        await asyncio.sleep(2 * ESTOP_CONFIRM_S)  # a service that answers too late …
        return {"ok": True}  # … and, here, does nothing

    monkeypatch.setattr(ControlServer, "_estop", late)

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await press_until(app, pilot, "e", lambda: "EMERGENCY STOP sent" in response(app), "e")
        await until(pilot, lambda: "NOT CONFIRMED" in response(app), "the wait given up")
        said = response(app)
        assert "(no answer within 0.5 s)" in said and "hardware emergency stop" in said
        assert not app.sup.estop
        app.refresh_view()
        assert not app.query_one("#estop").has_class("latched")

    run_app(check)


def test_the_command_line_shows_the_services_clamp_note(monkeypatch: pytest.MonkeyPatch) -> None:
    """The service's `command` result names the units whose value it clamped; the field
    is read if present (a service without it answers as before)."""
    note = "clamped: VEL 5000 0 → 1000 0 (limits.velocity 1000)"
    real = ControlServer._command

    async def command(self: ControlServer, client: Any, params: dict[str, Any]) -> Any:
        result = dict(await real(self, client, params))
        if "5000" in params["text"]:
            result.setdefault("clamped", {"left": note})
            result.setdefault("responses", {"left": result["response"]})
        return result

    monkeypatch.setattr(ControlServer, "_command", command)
    config = (
        "buses:\n  b: {interface: virtual, channel: t, simulate: true}\n"
        "units:\n  - {name: left, abh3_id: 1, limits: {velocity: 1000}}\n"
    )

    async def command_line(app: SupervisorApp, pilot: Any, text: str) -> None:
        cmdline = app.query_one("#cmdline", Input)
        await press_until(app, pilot, "colon", lambda: app.focused is cmdline, ":")
        cmdline.value = text  # as typed
        await press_until(app, pilot, "enter", lambda: repr(text) in response(app), text)

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        for text in ("SERVO ON ON", "START ON ON"):  # a robot moves only while switched on
            await command_line(app, pilot, text)
        await command_line(app, pilot, "VEL 5000 0")
        assert response(app) == f"left ← 'VEL 5000 0' → '' · {note}"
        await command_line(app, pilot, "VEL 500 0")
        assert response(app) == "left ← 'VEL 500 0' → ''"  # nothing clamped: no note

    run_app(check, config)


def test_every_axis_value_carries_its_letter_at_every_width() -> None:
    """left is `travel` (Y/X), right `motor` (A/B): no header names channels, and every
    command, feedback, current and load cell says which axis each number is."""
    mirror = mirror_of(snapshot_rig())
    left, right = overview_row(mirror, "left"), overview_row(mirror, "right")
    letters = {"cmd": (("Y", "X"), ("A", "B")), "fbk": (("Y", "X"), ("A", "B"))}
    letters |= {"current": letters["cmd"], "load": (("A", "B"), ("A", "B"))}
    letters |= {"fbk A/B": (("A", "B"),) * 2, "fbk Y/X": (("Y", "X"),) * 2}
    axis_cell = r"(?P<a>[ABXY]) *-?[\d.–]+%? (?P<b>[ABXY]) *-?[\d.–]+%?"
    for width in range(40, 201):
        for column in overview.fit(width):
            assert not re.search(r"\b(AY|BX|A/Y|B/X)\b", column.header), (width, column)
            if column.key not in letters:
                continue
            for row, want in zip((left, right), letters[column.key], strict=True):
                m = re.fullmatch(axis_cell, row[column.key].strip())
                assert m and (m["a"], m["b"]) == want, (width, column.key, row[column.key])
    assert "cmd Y 300.0 X 20.0 min⁻¹" in detail_fields(mirror, "left")
    assert "cmd A 0.0 B 0.0 min⁻¹" in detail_fields(mirror, "right")
    assert "fbk A 320.0 B 280.0 min⁻¹" in detail_fields(mirror, "left")  # both, each named
    labels = [series_label(mirror.units[n], k) for n in ("left", "right") for k in ("cmd AY",)]
    assert labels == ["cmd Y", "cmd A"]
    assert series_label(mirror.units["right"], "current BX") == "current B"
    assert series_label(mirror.units["left"], "load B") == "load B"  # a motor's, always


def test_a_stale_overview_is_dimmed_and_says_how_old() -> None:
    mirror = mirror_of(snapshot_rig())
    text = overview.render(mirror, ["left", "right"], 0, 160, stale=3.24)
    lines = text.plain.splitlines()
    assert lines[0] == "STALE: these values are 3.2 s old, not live"
    assert all(" stale " in line for line in lines[2:4])
    assert {str(span.style) for span in text.spans if span.start > len(lines[0]) + 1} >= {"dim"}
    live = overview.render(mirror, ["left", "right"], 0, 160)
    assert "STALE" not in live.plain and " online " in live.plain


def test_a_state_sent_twice_does_not_undo_a_confirmed_estop() -> None:
    """The service may send one encoded state twice (shared for a few ms): the copy
    arriving after the e-stop's reply must not show the e-stop cleared again."""
    rig = snapshot_rig()
    mirror = mirror_of(rig)
    state = supervisor_state(rig.sup, {})
    mirror.estop = True  # the reply confirmed it
    assert not mirror.apply(state) and mirror.estop
    rig.run(0.1)
    assert mirror.apply(supervisor_state(rig.sup, {})) and not mirror.estop  # newer: taken
