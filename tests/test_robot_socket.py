"""The control socket's ``twist`` drives a robot as a whole: a robot on two drives (one
wheel per drive) and a skid-steer on two drives, every wheel's speed in one scheduler
turn with the robot's mounting signs, one clamp for the robot, one owner per robot, and
the e-stop on all its drives."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients.control import ControlClient
from abh3_supervisor.errors import RunError
from tests.support.robots import SKID, TWO_DRIVES, first_moving, in_one_turn, motor, sent
from tests.support.served import Served, wait_for
from tests.support.wire_monitor import WireMonitor

pytestmark = pytest.mark.wallclock  # real time: a runtime and its socket


def running(served: Served, units: list[str]) -> ControlClient:
    client = ControlClient(served.path)
    for text in ("SERVO ON ON", "START ON ON"):
        assert client.call("command", units=units, text=text)["response"] == ""
    return client


def setpoints(served: Served) -> dict[str, Any]:
    assert served.rt is not None
    units = served.rt.supervisor.units
    found: dict[str, Any] = served.on_loop(
        lambda: {n: (u.setpoint.ay, u.setpoint.bx, u.setpoint.owner) for n, u in units.items()}
    )
    return found


@pytest.mark.parametrize(
    ("config", "robot", "expect"),
    [
        # left wheel forward, right wheel mounted mirrored: its motor turns backwards
        (TWO_DRIVES, "rover", lambda m: {"l": (m, 0.0), "r": (-m, 0.0)}),
        (SKID, "skid", lambda m: {"front": (m, -m), "rear": (m, -m)}),
    ],
)
def test_a_twist_to_a_robot_reaches_every_drive_in_one_turn_with_its_signs(
    tmp_path: Path, config: str, robot: str, expect: Any
) -> None:
    with Served(tmp_path, config) as served:
        assert served.rt is not None
        units = served.rt.config.robots[robot].units
        client = running(served, list(units))
        seen = served.on_loop(sent, served.rt.supervisor)
        wheel = served.rt.config.robots[robot].wheels[0]
        m = motor(0.1, wheel.diameter_m, wheel.gear_ratio)
        try:
            reply = client.call("twist", robot=robot, linear_x=0.1, angular_z=0.0)
            assert reply == {"ok": True, "fresh_for_s": 0.5, "robots": [robot]}
            wait_for(lambda: first_moving(seen, units) is not None, "every drive moving")
            first = first_moving(seen, units)
            assert first is not None and in_one_turn(first)
            for unit, pair in expect(m).items():
                assert (first[unit].ay, first[unit].bx) == pytest.approx(pair, abs=0.2)
            owners = {sp[2] for sp in setpoints(served).values()}
            assert owners == {f"{client.call('hello')['name']}:{robot}"}  # one source
        finally:
            client.close()


def test_a_straight_twist_beyond_one_sides_limit_stays_straight(tmp_path: Path) -> None:
    with Served(tmp_path, TWO_DRIVES) as served:
        client = running(served, ["l", "r"])
        try:
            client.call("twist", units=["l"], linear_x=5.0, angular_z=0.0)  # a unit: its robot
            sp = setpoints(served)
            # the left drive's 1000 min⁻¹ binds: both sides at it, so the robot goes straight
            assert sp["l"][:2] == pytest.approx((1000.0, 0.0))
            assert sp["r"][:2] == pytest.approx((-1000.0, 0.0))
        finally:
            client.close()


def test_another_clients_twist_or_vel_on_the_robot_takes_all_of_it(tmp_path: Path) -> None:
    with Served(tmp_path, TWO_DRIVES) as served:
        first = running(served, ["l", "r"])
        second = ControlClient(served.path)
        try:
            first.call("twist", robot="rover", linear_x=0.1, angular_z=0.0)
            name = second.call("hello")["name"]
            # a VEL on one drive of the robot: the whole robot is the second client's
            held = second.call("command", unit="r", text="VEL 50 0")
            assert held["held"] is True
            sp = setpoints(served)
            assert sp["r"] == (50.0, 0.0, f"{name}:rover")
            assert sp["l"][:2] == (0.0, 0.0)  # never two owners: the other drive stops
            lost = first.call("alive")["lost"]
            assert lost == dict.fromkeys(("l", "r"), f"taken over by {name}:rover")
            assert second.call("alive") == {"ok": True, "holds": ["r"], "lost": {}}
        finally:
            second.close()
            first.close()


def test_another_clients_twist_on_the_robot_is_arbitrated_as_for_units(tmp_path: Path) -> None:
    with Served(tmp_path, TWO_DRIVES) as served:
        first = running(served, ["l", "r"])
        second = ControlClient(served.path)
        try:
            one, two = first.call("hello")["name"], second.call("hello")["name"]
            first.call("twist", robot="rover", linear_x=0.1, angular_z=0.0)
            second.call("twist", unit="r", linear_x=0.0, angular_z=0.5)  # later: it wins
            sp = setpoints(served)
            assert {sp[u][2] for u in ("l", "r")} == {f"{two}:rover"}
            assert sp["l"][0] < 0 and sp["r"][0] < 0  # turning left: both motors backwards
            assert first.call("alive")["lost"] == dict.fromkeys(
                ("l", "r"), f"taken over by {two}:rover"
            )
            first.call("twist", robot="rover", linear_x=0.1, angular_z=0.0)  # and back
            assert {sp[2] for sp in setpoints(served).values()} == {f"{one}:rover"}
        finally:
            second.close()
            first.close()


def test_a_vel_on_both_drives_of_a_robot_moves_both(tmp_path: Path) -> None:
    with Served(tmp_path, TWO_DRIVES) as served:
        client = running(served, ["l", "r"])
        try:
            assert client.call("command", units=["l", "r"], text="VEL 100 0")["held"] is True
            assert client.call("alive") == {"ok": True, "holds": ["l", "r"], "lost": {}}
            sp = setpoints(served)
            assert sp["l"][:2] == sp["r"][:2] == (100.0, 0.0)
            # then a twist of the same client: its own, replacing the VEL, nothing lost
            client.call("twist", robot="rover", linear_x=0.1, angular_z=0.0)
            assert client.call("alive") == {"ok": True, "holds": [], "lost": {}}
        finally:
            client.close()


def test_the_estop_stops_the_whole_robot_and_refuses_its_twist(
    tmp_path: Path, wire: WireMonitor
) -> None:
    with Served(tmp_path, SKID) as served:
        assert served.rt is not None
        sup = served.rt.supervisor
        client = running(served, ["front", "rear"])
        try:
            client.call("twist", robot="skid", linear_x=0.0, angular_z=1.0)
            sp = setpoints(served)
            assert all(sp[u][0] and sp[u][1] for u in ("front", "rear"))
            client.call("estop")
            wire.estop()
            assert setpoints(served) == dict.fromkeys(("front", "rear"), (0.0, 0.0, None))
            with pytest.raises(RunError, match="emergency stop"):
                client.call("twist", robot="skid", linear_x=0.1, angular_z=0.0)
            with pytest.raises(RunError, match="emergency stop"):
                client.call("twist", unit="rear", linear_x=0.1, angular_z=0.0)
            assert served.on_loop(lambda: sup.estop)
        finally:
            client.close()


def test_a_twist_names_robots_it_knows(tmp_path: Path) -> None:
    with Served(tmp_path, TWO_DRIVES) as served:
        client = ControlClient(served.path)
        try:
            assert client.call("hello")["robots"] == {"rover": ["l", "r"]}
            with pytest.raises(RunError, match=r"no robot or unit named 'tank' \(robots: rover\)"):
                client.call("twist", robot="tank", linear_x=0.1, angular_z=0.0)
            with pytest.raises(RunError, match="give 'robot'"):
                client.call("twist", robots=[], linear_x=0.1, angular_z=0.0)
        finally:
            client.close()


def test_a_velocity_in_torque_mode_or_to_a_robot_not_switched_on_is_refused_in_its_answer(
    tmp_path: Path,
) -> None:
    """The socket's answer says what the decision says (docs/safety.md, "The robot
    decision"): it once answered ``ok`` to a velocity that could never move (torque mode),
    and to a twist while a drive of the robot was not switched on."""
    with Served(tmp_path, TWO_DRIVES) as served:
        assert served.rt is not None
        units = served.rt.supervisor.units
        wait_for(lambda: all(u.online for u in units.values()), "both drives heard")
        client = ControlClient(served.path)
        try:
            with pytest.raises(
                RunError, match=r"may not move: l: SERVO A, START A not switched on"
            ):
                client.call("twist", robot="rover", linear_x=0.1, angular_z=0.0)
            running(served, ["l", "r"])
            assert client.call("command", unit="l", text="TORQUE ON ON")["response"] == ""
            with pytest.raises(RunError, match=r"in current mode; a velocity command needs"):
                client.call("velocity", unit="l", ay=100.0, bx=0.0)
        finally:
            client.close()


def test_enable_switches_the_robot_on_as_one_act_and_names_the_drive_that_did_not_follow(
    tmp_path: Path,
) -> None:
    from abh3_supervisor.clients import control
    from abh3_supervisor.protocol import flags

    with Served(tmp_path, TWO_DRIVES) as served:
        assert served.rt is not None
        rt = served.rt
        units = rt.supervisor.units
        wait_for(lambda: all(u.online for u in units.values()), "both drives heard")
        assert control.enable(served.path, ["rover"], on=True) == 0
        for name, lay in (("l", flags.LAYOUT_2021), ("r", flags.LAYOUT_2023)):
            word = served.on_loop(lambda n=name: units[n].inputs)
            assert word & (lay.servo.ay | lay.start.ay) == lay.servo.ay | lay.start.ay
            assert not word & (lay.servo.bx | lay.start.bx)  # B drives no wheel
        assert control.enable(served.path, ["rover"], on=False) == 0
        assert served.on_loop(lambda: rt.supervisor.robot_unready("l")) is not None
        # a drive that does not follow (its servo held off by an error): named, exit 1
        drive = rt.sims["b"].drives[3]
        served.on_loop(lambda: setattr(drive, "errors", 1 << 2))  # driver overheat
        with pytest.raises(RunError, match=r"not every drive followed: robot rover: r: "):
            control.enable(served.path, ["rover"], on=True)


def test_enable_of_a_robot_that_does_not_exist_is_a_command_line_mistake(
    tmp_path: Path,
) -> None:
    from abh3_supervisor.clients import control
    from abh3_supervisor.errors import Abh3Error

    with Served(tmp_path, TWO_DRIVES) as served:
        with pytest.raises(
            Abh3Error, match=r"no robot or unit named 'nosuchbot' \(robots: rover\)"
        ) as err:
            control.enable(served.path, ["nosuchbot"], on=True)
        assert not isinstance(err.value, RunError)  # exit 2, not 1
