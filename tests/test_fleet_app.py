"""``abh3 fleet``'s view driven by a Textual pilot, fed hand-made payloads through a fake
link (no network, a fake clock): what it shows, what its keys publish, what it says of
the answers, and the attach key."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import Awaitable, Callable

import pytest
from rich.text import Text
from textual.widgets import Static

from abh3_supervisor.clients.fleet.app import FleetApp, attach_argv
from abh3_supervisor.clients.fleet.broker import Received
from abh3_supervisor.clients.fleet.commands import Commander
from abh3_supervisor.clients.fleet.model import FleetModel
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from tests.support.fleet_payloads import PREFIX, T0, state_topic, status, status_topic, unit_state

A, B = "plant-a", "plant-b"
ATTACH = "ssh://agv@plant-b/run/abh3/robot.sock"


class FakeLink:
    def __init__(self) -> None:
        self.connected = True
        self.inbox: list[Received] = []
        self.published: list[tuple[str, dict[str, object]]] = []
        self.acks: list[tuple[int, int, str]] = []

    def drain(self) -> list[Received]:
        out, self.inbox = self.inbox, []
        return out

    def take_acks(self) -> list[tuple[int, int, str]]:
        out, self.acks = self.acks, []
        return out

    def publish(self, topic: str, payload: bytes) -> tuple[int, str | None]:
        self.published.append((topic, json.loads(payload)))
        return len(self.published), None

    def describe(self, now: float) -> str:
        if not self.connected:
            return "broker: LOST 5 s ago (Unspecified error); reconnecting"
        return "broker: connected to mqtt://127.0.0.1:1883 (MQTT 5) as me"


class Clock:
    def __init__(self) -> None:
        self.now = T0

    def __call__(self) -> float:
        return self.now


Check = Callable[[FleetApp, object, FakeLink, Clock], Awaitable[None]]


def fleet_of_two(link: FakeLink, at: float) -> None:
    link.inbox += [
        Received(status_topic(A), status(A, time=at - 30), True, at),
        Received(status_topic(B), status(B, time=at - 30, attach=ATTACH), True, at),
    ]
    for fid in (A, B):
        for unit in ("left", "right"):
            link.inbox.append(Received(state_topic(fid, unit), unit_state(fid, unit, time=at), False, at))  # fmt: skip


def screen_text(app: FleetApp, only: str | None = None) -> str:
    """The head and the list (or ``only`` one of them, by id)."""
    shown = []
    for part in ("fleet-head", "fleet") if only is None else (only,):
        content = app.query_one(f"#{part}", Static).content
        assert isinstance(content, Text)
        shown.append(content.plain)
    return "".join(shown)


def run(check: Check, v5: bool = True) -> None:
    asyncio.run(running(check, v5))


async def running(check: Check, v5: bool) -> None:
    link, clock = FakeLink(), Clock()
    fleet_of_two(link, clock.now)
    app = FleetApp(
        FleetModel(PREFIX, 2.0), Commander("me", PREFIX, v5=v5), link, "test", clock=clock
    )
    async with app.run_test(size=(150, 40)) as pilot:
        await pilot.pause()
        await check(app, pilot, link, clock)


def test_every_unit_grouped_by_robot_and_greyed_once_stale() -> None:
    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        text = screen_text(app)
        assert text.index(A) < text.index("left") < text.index(B)
        assert text.count("ONLINE") == 2 and "stale" not in text
        assert f"▶ {A}" in text
        clock.now += 3.0
        app.tick()
        text = screen_text(app)
        assert text.count("(stale)") == 4 and "3.0 s" in text
        link.inbox.append(Received(status_topic(A), status(A, "connection_broken"), False, clock.now))  # fmt: skip
        app.tick()
        assert "CONNECTION BROKEN" in screen_text(app)
        link.connected = False
        app.tick()
        text = screen_text(app)
        assert "broker: LOST" in text and "ONLINE (last known: broker lost)" in text

    run(check)


def test_e_stops_the_selected_robot_at_once_and_says_what_came_of_it() -> None:
    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        await pilot.press("down", "e")  # type: ignore[attr-defined]
        topic, body = link.published[-1]
        assert topic == f"{PREFIX}/{B}/cmd/estop"
        assert (body["v"], body["seq"], body["sender"], body["reason"]) == (1, 1, "me", "test")
        assert body["time"] == clock.now
        link.acks.append((1, 0, "Success"))
        app.tick()
        assert f"e-stop {B} (seq 1): taken by the broker" in screen_text(app)
        clock.now += 0.3
        for unit in ("left", "right"):
            link.inbox.append(Received(state_topic(B, unit), unit_state(B, unit, estop=True, time=clock.now), False, clock.now))  # fmt: skip
        app.tick()
        assert f"e-stop {B} (seq 1): latched on {B}" in screen_text(app)

    run(check)


def test_the_selection_scrolls_into_sight_and_the_head_stays() -> None:
    """25 robots of 2 units do not fit in 40 rows: ↓ moves the selection, the list
    follows it, and the command's outcome stays in sight."""

    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        many = [f"r{i:02}" for i in range(25)]
        for fid in many:
            link.inbox.append(Received(status_topic(fid), status(fid, time=clock.now), True, clock.now))  # fmt: skip
            for unit in ("left", "right"):
                link.inbox.append(Received(state_topic(fid, unit), unit_state(fid, unit, time=clock.now), False, clock.now))  # fmt: skip
        app.tick()
        for _ in range(20):
            await pilot.press("down")  # type: ignore[attr-defined]
        await pilot.pause()  # type: ignore[attr-defined]
        order = sorted([A, B, *many])
        assert app.selected == order[20]
        await pilot.press("e")  # type: ignore[attr-defined]
        assert link.published[-1][0] == f"{PREFIX}/{order[20]}/cmd/estop"
        app.tick()
        await pilot.pause()  # type: ignore[attr-defined]
        head = app.query_one("#fleet-head", Static)
        assert f"e-stop {order[20]} (seq 1)" in str(head.content)
        assert head.region.y == 0  # above the list, never scrolled
        lines = screen_text(app, "fleet").splitlines()
        row = next(i for i, line in enumerate(lines) if line.startswith(f"▶ {order[20]}"))
        top = round(app.scroller.scroll_y)
        assert top <= row < top + app.scroller.scrollable_content_region.height

    run(check)


def test_a_refusal_by_the_broker_is_said() -> None:
    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        await pilot.press("e")  # type: ignore[attr-defined]
        link.acks.append((1, 0x87, "Not authorized"))
        app.tick()
        assert "REFUSED by the broker: Not authorized (0x87)" in screen_text(app)

    run(check)


def test_under_3_1_1_it_is_sent_not_confirmed_until_the_robot_shows_it() -> None:
    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        await pilot.press("e")  # type: ignore[attr-defined]
        link.acks.append((1, 0, "Success"))
        app.tick()
        assert "sent, not confirmed" in screen_text(app)

    run(check, v5=False)


def test_e_always_e_stops_no_palette_and_no_question_takes_it() -> None:
    """No command palette (its search line took `e`, and ctrl+p opened it from the
    footer); `e` and ctrl+e e-stop the selected robot even with a question open."""

    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        press = pilot.press  # type: ignore[attr-defined]
        await press("ctrl+p", "e")
        assert [t for t, _ in link.published] == [f"{PREFIX}/{A}/cmd/estop"]
        await press("c")  # the clear question open: e is still the e-stop
        assert isinstance(app.screen, ConfirmScreen)
        await press("e")
        await press("ctrl+e")
        assert [t for t, _ in link.published][1:] == [f"{PREFIX}/{A}/cmd/estop"] * 2
        await press("y")  # and the question is still there to answer
        assert link.published[-1][0] == f"{PREFIX}/{A}/cmd/estop_clear"

    run(check)


def test_e_stop_all_and_clear_are_asked_first() -> None:
    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        press = pilot.press  # type: ignore[attr-defined]
        await press("E")
        assert isinstance(app.screen, ConfirmScreen) and link.published == []
        link.inbox.append(Received(status_topic(A), status(A, "offline"), False, clock.now))
        app.tick()  # the view keeps up under the question
        assert "offline" in screen_text(app)
        await press("n")
        assert link.published == []
        await press("E", "y")
        assert link.published[-1][0] == f"{PREFIX}/all/cmd/estop"
        await press("c")
        assert isinstance(app.screen, ConfirmScreen)
        await press("enter")  # No has the focus: Enter never clears by accident
        assert len(link.published) == 1
        await press("c", "y")
        assert link.published[-1][0] == f"{PREFIX}/{A}/cmd/estop_clear"
        await press("C", "y")
        assert link.published[-1][0] == f"{PREFIX}/all/cmd/estop_clear"
        assert [b["seq"] for _, b in link.published] == [1, 2, 3]

    run(check)


def test_attach_runs_the_robots_tui_or_says_why_not(monkeypatch: pytest.MonkeyPatch) -> None:
    ran: list[list[str]] = []

    def run_attached(self: FleetApp, argv: list[str]) -> int:
        ran.append(argv)
        return 0

    monkeypatch.setattr(FleetApp, "run_attached", run_attached)

    async def check(app: FleetApp, pilot: object, link: FakeLink, clock: Clock) -> None:
        press = pilot.press  # type: ignore[attr-defined]
        await press("a")  # plant-a publishes no attach
        assert ran == []
        assert any("publishes no attach address" in n.message for n in app._notifications)
        await press("down", "a")
        assert ran == [attach_argv(ATTACH)]
        assert ran[0][-3:] == ["tui", "--connect", ATTACH]

    run(check)


def test_only_an_ssh_address_is_attached() -> None:
    assert attach_argv("--exec=rm -rf /") is None
    assert attach_argv("ssh://a@b/x.sock --evil") is None
    assert attach_argv("/run/abh3.sock") is None


def test_without_paho_it_says_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from abh3_supervisor.clients import cli

    for name in ("paho", "paho.mqtt", "paho.mqtt.client", "paho.mqtt.enums"):
        monkeypatch.setitem(sys.modules, name, None)  # an import of it fails
    assert cli.main(["fleet", "--broker", "mqtt://127.0.0.1:1883"]) == 1
    assert capsys.readouterr().err == (
        "error: paho-mqtt is not installed: pip install 'abh3-supervisor[mqtt]' (in a clone: "
        "pip install -e '.[mqtt]')\n"
    )
