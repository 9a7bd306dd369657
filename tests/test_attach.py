"""The TUI as a client of a running supervisor: attach, detach, several clients, the
service gone, and the TUI's own process dying (`abh3 tui` and `abh3 run` on a terminal)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients.link import Link
from abh3_supervisor.clients.tui.app import SupervisorApp
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.server import ControlServer
from tests.support.headless import headless_demo
from tests.support.safe_word import assert_demo_stopped
from tests.support.served import served, wait_for
from tests.support.terminal import in_a_terminal
from tests.support.tui import attached, response, until
from tests.support.wire_monitor import WireMonitor

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.wallclock
def test_two_clients_detach_and_reattach_while_the_drives_keep_their_rate(
    wire: WireMonitor,
) -> None:
    async def check(rt: Runtime, server: ControlServer, path: Path) -> None:
        sup = rt.supervisor
        for text in ("SERVO ON ON", "START ON ON"):
            assert await sup.command("left", text) == ""
        app, link = await attached(path, owner=False)
        other = await Link.open(path)  # a second client: a script
        try:
            async with app.run_test(size=(160, 45)) as pilot:
                reply = await other.call("command", unit="left", text="VEL 100 0")
                assert reply["response"] == "" and reply["held"] is True
                await until(pilot, lambda: app.sup.units["left"].setpoint.ay == 100, "VEL shown")
                assert await other.call("estop") == {"ok": True}
                wire.estop()
                await until(pilot, lambda: app.sup.estop, "the other client's e-stop shown")
                assert sup.units["left"].setpoint.ay == 0  # zero on the next command frame
                app.refresh_view()
                assert app.query_one("#estop").has_class("latched")
                await pilot.press("q")  # detaching asks, and says the drives keep running
                await pilot.pause()
                assert isinstance(app.screen, ConfirmScreen)
                assert "keeps running" in app.screen.question
                assert "motion this TUI commanded" in app.screen.question
                assert "stops at once" in app.screen.question
                await pilot.press("y")
            await link.close()
            sent = sup.schedulers["b"].slots["left"].stats.commands_sent
            await sup.wait_exchange("left", sup.clock(), 1.0)
            assert sup.schedulers["b"].slots["left"].stats.commands_sent > sent  # still running
            # the e-stop powered it off once it reported stopped (stop category 1)
            assert not sup.units["left"].inputs & sup.units["left"].layout.servo.both
            assert not sup.stopping
            again, link2 = await attached(path, owner=False)  # re-attach: the same state
            async with again.run_test(size=(160, 45)) as pilot:
                assert again.sup.estop
                await pilot.press("E", "y")
                await until(pilot, lambda: not sup.estop, "cleared from the re-attached TUI")
                st = sup.schedulers["b"].slots["left"].stats  # never a gap the drive saw
                assert sup.units["left"].online and st.gaps == 0
            await link2.close()
        finally:
            await other.close()

    served(check)


@pytest.mark.wallclock
def test_the_service_gone_is_shown_at_once_and_keys_say_so() -> None:
    async def check(rt: Runtime, server: ControlServer, path: Path) -> None:
        app, link = await attached(path, owner=True)
        async with app.run_test(size=(160, 45)) as pilot:
            for client in list(server.clients):  # a crash: no "bye", the socket just ends
                client.writer.close()
            await until(pilot, lambda: app.gone is not None, "the loss seen")
            banner = str(app.query_one("#gone").render())
            assert banner.startswith("NOT CONNECTED") and app.query_one("#gone").has_class("shown")
            await pilot.press("v")
            assert "not connected" in response(app)
            await pilot.press("q")  # nothing to stop from here: leaves without asking
            await pilot.pause()
            assert not app.is_running
        await link.close()

    served(check)


@pytest.mark.wallclock
def test_an_orderly_stop_is_shown_as_one_not_as_a_supervisor_that_died() -> None:
    """A "bye" (the supervisor stopping: it stops its drives itself, after telling its
    clients) is not the crash's warning that nothing stops the drives."""

    async def check(rt: Runtime, server: ControlServer, path: Path) -> None:
        app, link = await attached(path, owner=False)
        async with app.run_test(size=(160, 45)) as pilot:
            await server.close()
            await until(pilot, lambda: app.gone is not None, "the bye seen")
            banner = str(app.query_one("#gone").render())
            assert banner.startswith("NOT CONNECTED: the supervisor is stopping: it sends zero")
            assert "stops nothing by itself" not in banner
        await link.close()

    served(check)


def _status(sock: Path) -> dict[str, Any]:
    out = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "status", "--json", "--connect", str(sock)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=30,
    )
    state: dict[str, Any] = json.loads(out.stdout)
    return state


@pytest.mark.wallclock
def test_kill_9_of_an_attached_tui_changes_nothing_on_the_bus(tmp_path: Path) -> None:
    sock = Path(tempfile.mkdtemp(dir="/tmp")) / "demo.sock"
    with headless_demo(sock):
        pid, fd = in_a_terminal(["tui", "--connect", str(sock)])
        before = _status(sock)
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(fd)
        after = _status(sock)  # demo.yaml drives both units from its startup commands
        for name in ("left", "right"):
            b, a = before["units"][name], after["units"][name]
            assert a["online"] and a["setpoint"] == b["setpoint"]
            assert a["words"]["control"]["value"] == b["words"]["control"]["value"]
            assert a["stats"]["replies"] > b["stats"]["replies"]  # exchanges go on
            assert a["stats"]["gaps"] == 0  # never a gap the drive saw
        assert not after["estop"] and not after["stopping"]


@pytest.mark.wallclock
def test_kill_9_of_the_tui_that_started_the_supervisor_stops_the_drives(
    tmp_path: Path,
) -> None:
    """`abh3 run` on a terminal: the supervisor is a child; the TUI dying closes the pipe
    the child reads, and the child stops every drive."""
    sock = Path(tempfile.mkdtemp(dir="/tmp")) / "demo.sock"
    record = tmp_path / "run.log"
    pid, fd = in_a_terminal(
        ["run", "configs/demo.yaml", "--socket", str(sock), "--record", str(record)]
    )
    assert _status(sock)["units"]["left"]["online"]
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    os.close(fd)
    wait_for(lambda: not sock.exists(), "the child stops serving")
    log = sock.with_name(sock.name + ".log")
    wait_for(lambda: log.read_text().count("stop frame confirmed") == 2, "both stops confirmed")
    wait_for(lambda: "recorded" in log.read_text(), "the recording closed")
    assert_demo_stopped(record)


def test_taken_keys_are_the_apps_own() -> None:
    taken = SupervisorApp.taken_keys()
    assert {"e", "q", "E", "+", ":", "?"} <= set(taken)
