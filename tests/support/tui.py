"""The TUI on a supervisor served in-process: attached as `abh3 tui` attaches, driven by a
Textual pilot, and what its tests wait for."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from textual import events

from abh3_supervisor.clients.link import Link
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui.app import STATE_HZ, SupervisorApp
from abh3_supervisor.config import parse_config
from abh3_supervisor.core.inputs import InputCommand, Twist
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.plugin_host import terminal
from abh3_supervisor.protocol import flags
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.service.server import ControlServer
from abh3_supervisor.service.snapshot import supervisor_state
from tests.support.rig import TWO_UNITS, Rig, present, set_velocity
from tests.support.served import served

KEYBOARD = TWO_UNITS + "plugins:\n  keyboard: {units: [left]}\n"


async def attached(path: Path, owner: bool = True) -> tuple[SupervisorApp, Link]:
    """The app on the socket, set up as `abh3 tui`/`abh3 run` set it up."""
    link = await Link.open(path)
    hello = await link.call("hello", name="tui")
    mirror = Mirror.from_hello(hello)
    mirror.apply(await link.call("state"))
    keys = await link.call("keys", taken=SupervisorApp.taken_keys())
    app = SupervisorApp(mirror, link, owner=owner, plugin_keys=keys)
    await link.call("subscribe", events=True, state_hz=STATE_HZ)
    return app, link


def run_app(
    check: Any,
    config: str = TWO_UNITS,
    size: tuple[int, int] = (160, 45),
    own_terminal: bool = False,
) -> None:
    """Run the app on the real runtime (virtual bus, simulated drives) over its control
    socket, with a pilot; the check sees the runtime too."""

    async def with_app(rt: Runtime, server: ControlServer, path: Path) -> None:
        app, link = await attached(path)
        try:
            async with app.run_test(size=size) as pilot:
                await check(app, pilot, rt)
        finally:
            await link.close()

    if own_terminal:  # the service of a TUI: keyboard plugins take their keys from it
        terminal.claim("the TUI")
    try:
        served(with_app, config)
    finally:
        terminal.release()


def response(app: SupervisorApp) -> str:
    return str(app.query_one("#response").render())


def twists_applied(sup: Supervisor) -> list[tuple[str, float, float]]:
    """Every twist the arbitration applies to a unit from now on, as (unit, x, z)."""
    driven: list[tuple[str, float, float]] = []
    real = sup.arbiter.apply

    def spy(name: str, command: InputCommand) -> bool | None:
        if isinstance(command, Twist):
            driven.append((name, command.linear_x, command.angular_z))
        return real(name, command)

    sup.arbiter.apply = spy
    return driven


async def until(pilot: Any, condition: Any, what: str) -> None:
    """Let the app and the buses run until ``condition()`` holds (bounded: 15 s, for a
    loaded machine; a condition that holds returns at once)."""
    for _ in range(1500):
        if condition():
            return
        await pilot.pause(0.01)
    raise AssertionError(f"never happened: {what}")


async def press_until(app: SupervisorApp, pilot: Any, key: str, done: Any, what: str) -> None:
    """A key as the terminal driver delivers it, then ``until(pilot, done)``.

    ``pilot.press`` waits after each key for the *process* to look idle (Textual's
    ``wait_for_idle``: under 1 ms of CPU in 20 ms, else up to 1 s); the buses and simulated
    drives in this process rarely allow that, so 300 keys would take minutes.
    """
    app.post_message(events.Key(key, key if len(key) == 1 else None))
    await until(pilot, done, what)


def mirror_of(rig: Rig) -> Mirror:
    """What a client of this rig's supervisor would know now."""
    mirror = Mirror.of(rig.config, tuple(rig.config.buses))
    mirror.apply(supervisor_state(rig.sup, {}))
    return mirror


def snapshot_rig() -> Rig:
    """Two units after 30 s of fake time: left driven (forward, then back), right switched
    on, then tripped by an error (its SERVO forgotten: no automatic restart), with an alarm
    too; the plots have their whole window."""
    rig = Rig(parse_config(TWO_UNITS, "t.yaml"))
    for unit in ("left", "right"):
        rig.sup.apply_text(unit, "SERVO ON ON")
    rig.sup.apply_text("left", "START ON ON")
    set_velocity(rig.sup, "left", 300, 20, source=present(rig.sup, "left"))
    rig.run(1.0)
    rig.drive("right").errors = flags.FAULT.mask("A_OVERCURRENT")
    rig.drive("right").alarms = flags.FAULT.mask("CONTROL_UNDERVOLTAGE")
    rig.run(1.0)
    return rig
