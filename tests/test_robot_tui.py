"""The TUI's arrows drive a robot as a whole: the selected unit's robot, every drive of it
in the same scheduler turn with the robot's signs; the fastest twist the arrows ask comes
from the robot's kinematics and limits; the e-stop stops all of it."""

from __future__ import annotations

from typing import Any

import pytest

from abh3_supervisor.clients.tui import operator
from abh3_supervisor.clients.tui.app import SupervisorApp
from abh3_supervisor.clients.tui.screens import ConfirmScreen
from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime.bus_runtime import Runtime
from tests.support.rig import Rig, present, set_twist
from tests.support.robots import SKID, TWO_DRIVES, first_moving, in_one_turn, motor, sent
from tests.support.tui import mirror_of, press_until, response, run_app, until
from tests.support.wire_monitor import WireMonitor

pytestmark = pytest.mark.wallclock  # the app on a runtime over its socket


async def running(app: SupervisorApp, pilot: Any, rt: Runtime, units: tuple[str, ...]) -> None:
    sup = rt.supervisor
    for unit in units:
        for text in ("SERVO ON ON", "START ON ON"):
            assert await sup.command(unit, text, source=present(sup, unit)) == ""
    # SERVO and START on as the drives report them: the arrows move the robot
    await until(pilot, lambda: operator.stillness(app.sup, units) is None, "servo, start on")


@pytest.mark.parametrize(
    ("config", "select", "expect"),
    [
        # the second unit selected: still its robot, both drives, left forward, right mirrored
        (TWO_DRIVES, "n", lambda m: {"l": (m, 0.0), "r": (-m, 0.0)}),
        (SKID, "", lambda m: {"front": (m, -m), "rear": (m, -m)}),
    ],
    ids=["two-drives", "skid-steer"],
)
def test_the_arrows_drive_the_selected_units_robot_in_one_turn(
    config: str, select: str, expect: Any
) -> None:
    robot = next(iter(parse_config(config, "t.yaml").robots.values()))
    units = robot.units
    wheel = robot.wheels[0]
    m = motor(0.2, wheel.diameter_m, wheel.gear_ratio)  # the arrows' default 0.2 m/s

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        await running(app, pilot, rt, robot.units)
        if select:
            await press_until(app, pilot, select, lambda: "selected" in response(app), select)
            assert response(app).endswith(
                f"(the arrows drive {robot.name} ({', '.join(robot.units)}))"
            )
        overview = str(app.query_one("#table").render())
        assert f"the arrows drive {robot.name} ({', '.join(robot.units)})" in overview
        seen = sent(rt.supervisor)
        await press_until(app, pilot, "up", lambda: first_moving(seen, units), "all moving")
        first = first_moving(seen, units)
        assert first is not None
        assert in_one_turn(first)
        for unit, pair in expect(m).items():
            assert (first[unit].ay, first[unit].bx) == pytest.approx(pair, abs=0.2)
        assert response(app).startswith(f"drive {robot.name} ({', '.join(robot.units)}): +0.20")
        owners = {rt.supervisor.units[u].setpoint.owner for u in robot.units}
        assert len(owners) == 1 and owners.pop().endswith(f":{robot.name}")  # type: ignore[union-attr]

    run_app(check, config)


def test_the_arrows_fastest_twist_is_what_the_robots_one_clamp_lets_through() -> None:
    limited = TWO_DRIVES.replace(
        "    track_m: 0.5\n",
        "    track_m: 0.5\n    limits: {linear_mps: 0.5, angular_radps: 1.0}\n",
    )
    # the travel model: the limit holds on the Y/X fields the drive reads
    travel = SKID.replace(
        "velocity_model: motor", "velocity_model: travel, limits: {velocity: 500}"
    )
    for config in (TWO_DRIVES, SKID, limited, travel):
        rig = Rig(parse_config(config, "t.yaml"))
        robot = next(iter(rig.config.robots.values()))
        speed, turn = operator.speed_caps(mirror_of(rig), robot.units[-1:])
        for twist, cap in (((100.0, 0.0), speed), ((0.0, 100.0), turn)):
            set_twist(rig.sup, robot.name, *twist, source=present(rig.sup, robot.units[0]))
            plan = rig.sup.robots[robot.name].last
            assert plan is not None
            assert max(abs(v) for v in plan.twist) == pytest.approx(cap)
    # two drives: the left drive's 1000 min⁻¹ binds straight ahead
    rig = Rig(parse_config(TWO_DRIVES, "t.yaml"))
    assert operator.speed_caps(mirror_of(rig), ("l",))[0] == pytest.approx(1000 / motor(1, 0.3, 10))
    rig = Rig(parse_config(limited, "t.yaml"))
    assert operator.speed_caps(mirror_of(rig), ("r",)) == pytest.approx((0.5, 1.0))


def test_the_estop_stops_every_drive_of_the_robot_the_arrows_drive(wire: WireMonitor) -> None:
    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor
        await running(app, pilot, rt, ("front", "rear"))
        driving = lambda: all(sup.units[u].setpoint.ay for u in ("front", "rear"))  # noqa: E731
        await press_until(app, pilot, "left", driving, "turning on the spot")
        await press_until(app, pilot, "e", lambda: app.sup.estop, "the e-stop confirmed")
        wire.estop()
        assert all(
            sup.units[u].setpoint.ay == sup.units[u].setpoint.bx == 0 for u in ("front", "rear")
        )
        app.say("")
        await press_until(app, pilot, "up", lambda: bool(response(app)), "refused")
        assert response(app).startswith("EMERGENCY STOP latched")
        assert all(sup.units[u].setpoint.ay == 0 for u in ("front", "rear"))

    run_app(check, SKID)


def test_o_switches_the_robot_on_as_one_act_and_the_overview_says_whether_it_is_ready() -> None:
    """`o` asks, then enables the selected unit's robot (SERVO and START on every wheel axis
    of its drives, never on an axis that drives no wheel); the overview names the robot
    READY once the service says every drive reports it, and says why not, by drive, when a
    drive falls silent; `o` again switches it off at once."""
    robot = next(iter(parse_config(TWO_DRIVES, "t.yaml").robots.values()))

    async def check(app: SupervisorApp, pilot: Any, rt: Runtime) -> None:
        sup = rt.supervisor

        def overview() -> str:
            return str(app.query_one("#table").render())

        await until(pilot, lambda: f"robot {robot.name} not ready" in overview(), "not ready")
        await pilot.press("o")
        await pilot.pause()
        assert isinstance(app.screen, ConfirmScreen)
        assert f"Switch robot {robot.name} on?" in app.screen.question
        await press_until(app, pilot, "y", lambda: "READY" in response(app), "enabled")
        for name in robot.units:
            lay = sup.units[name].layout
            assert sup.units[name].inputs & (lay.servo.ay | lay.start.ay)
            assert not sup.units[name].inputs & (lay.servo.bx | lay.start.bx)  # B: no wheel
        await until(pilot, lambda: f"robot {robot.name} READY" in overview(), "READY shown")
        await pilot.press("n", "f")  # the right drive falls silent
        await until(
            pilot,
            lambda: f"robot {robot.name} not ready: r: " in overview().replace("\n", " "),
            "why not, by drive",
        )
        await pilot.press("f")  # it answers again: still off until switched on
        await press_until(app, pilot, "o", lambda: "SERVO and START off" in response(app), "off")

    run_app(check, TWO_DRIVES)
