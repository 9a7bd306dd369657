"""``abh3 fleet``'s client code — its broker client and session (model, commands), no
screen — and a real ``abh3 run --headless`` supervisor with the ``mqtt`` plugin (two
simulated drives on its own virtual bus), on the suite's Mosquitto
(tests/support/mosquitto.py). The view
sees the robot online and its units' states as the plugin publishes them; its e-stop to
all latches the supervisor's e-stop (said on the robot's state topics, and each drive's
stop frame read back from the bus recording); a clear it may not give is refused and
said; ``kill -9`` of the supervisor shows connection broken. Every payload the view
received validates against the contract's schemas."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from abh3_supervisor.clients.fleet.broker import BrokerOptions, FleetClient, Received
from abh3_supervisor.clients.fleet.commands import SENDING, Commander, Sent
from abh3_supervisor.clients.fleet.model import FleetModel
from abh3_supervisor.clients.fleet.session import Session
from abh3_supervisor.clients.fleet.view import render
from abh3_supervisor.fleet import PREFIX

pytest.importorskip("paho.mqtt.client", reason="paho-mqtt: pip install -e '.[mqtt]'")

from tests.support.mosquitto import FLEET, password, running
from tests.support.mqtt_watch import config, dp0_commands, schema_of, stop_frames, supervisor

pytestmark = pytest.mark.wallclock
NAME, FID = "e2e", "e2e-rover"
UNITS = ("front", "rear")
DRIVES = {1, 3}  # the units' abh3_id (tests/support/mqtt_watch.py, ROVER)
KEEPALIVE_S = 1


def wait_for(condition: Callable[[], object], what: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(0.01)


class View:
    """What ``abh3 fleet`` runs under its screen: its paho client and its ``Session`` (the
    app's tick and send); every payload received is checked against its schema first."""

    def __init__(self, port: int) -> None:
        options = BrokerOptions(
            "127.0.0.1",
            port,
            tls=False,
            username=FLEET,
            password=password(FLEET),
            client_id="abh3-fleet-e2e",
        )
        self.client = FleetClient(options, PREFIX)
        self.session = Session(
            FleetModel(PREFIX), Commander(options.client_id, PREFIX), self, "e2e"
        )
        self.model, self.commander = self.session.model, self.session.commander
        self.invalid: list[str] = []
        self.connected = True  # (the Link's; the render below asks the client itself)

    # the Link the session reads: the client's, with the schemas checked on the way
    def drain(self) -> list[Received]:
        arrived = self.client.drain()
        for m in arrived:
            if (validator := schema_of(m.topic)) is not None:
                body = json.loads(m.payload)
                self.invalid += [f"{m.topic}: {e.message}" for e in validator.iter_errors(body)]
        return arrived

    def take_acks(self) -> list[tuple[int, int, str]]:
        return self.client.take_acks()

    def publish(self, topic: str, payload: bytes) -> tuple[int, str | None]:
        return self.client.publish(topic, payload)

    def describe(self, now: float) -> str:
        return self.client.describe(now)

    def send(self, target: str | None, *, clear: bool) -> Sent:
        sent = self.session.send(target, clear=clear)
        assert sent.broker == SENDING, sent.broker  # published, not queued for later
        return sent

    def until(self, condition: Callable[[], object], what: str, timeout: float = 10.0) -> None:
        def ticked() -> object:
            self.session.tick()
            return condition()

        wait_for(ticked, what, timeout)

    def text(self) -> str:
        now = time.time()
        latest = self.commander.latest()
        summary = latest.summary() if latest else None
        return render(self.model, now, FID, self.client.describe(now), summary).plain


def test_the_view_sees_a_supervisor_e_stops_it_and_sees_it_killed(tmp_path: Path) -> None:
    with running(tmp_path / "broker", {NAME: [FID]}) as broker:
        cfg = config(tmp_path, NAME, broker, allow_estop=True, keepalive_s=KEEPALIVE_S)
        recording = tmp_path / "bus.log"
        with supervisor(cfg, "--record", str(recording)) as run:
            view = View(broker.port)
            view.client.connect(timeout=10)
            try:
                _check(view, run.proc.pid, recording)
            finally:
                view.client.close()
            assert not view.invalid, view.invalid


def _check(view: View, pid: int, recording: Path) -> None:
    model = view.model

    def units_live_and_started() -> bool:
        robot = model.robots.get(FID)
        now = time.time()
        return (
            robot is not None
            and robot.online
            and all(u in robot.units and model.live(robot, robot.units[u], now) for u in UNITS)
            and all(robot.units[u].start == (True, True) for u in UNITS)
        )

    view.until(units_live_and_started, "the robot online, both units live and started", 30)
    robot = model.robots[FID]
    assert (robot.name, robot.declared, robot.pid) == ("rover", UNITS, pid)
    for name in UNITS:
        unit = robot.units[name]
        assert (unit.online, unit.servo, unit.estop, unit.verify) == (
            True,
            (True, True),
            False,
            "ok",
        )
        assert (unit.errors, unit.alarms, unit.foreign_host) == ((), (), None)
    assert "ONLINE" in view.text()
    started = time.time()  # the drives commanded with START on, as the bus shows:
    wait_for(
        lambda: {d for _, d, on in dp0_commands(recording, started) if on} == DRIVES,
        "a DP0 command with START on to each drive",
    )

    # e-stop all, from the view's command code
    sent = view.send(None, clear=False)
    assert sent.topic == f"{PREFIX}/all/cmd/estop"
    view.until(lambda: sent.robot_said.get(FID) == "latched", "the robot's units latched")
    assert sent.summary() == f"e-stop all (seq 1): latched on {FID}"
    kinds = {e.kind: e for e in robot.events}
    obeyed = kinds["fleet_command"].data
    assert (obeyed["sender"], obeyed["seq"], obeyed["kind"]) == ("abh3-fleet-e2e", 1, "estop")
    assert "abh3-fleet-e2e" in kinds["estop_latched"].data["source"]
    view.until(
        lambda: all(robot.units[u].start == (False, False) for u in UNITS),
        "the drives report START off",
    )
    # the drives' own stop: every DP0 command with START off on both axes came after it,
    # and each drive got one (the recording is flushed as the supervisor runs)
    wait_for(lambda: set(stop_frames(recording, started)) == DRIVES, "both stop frames")
    assert min(stop_frames(recording, started).values()) >= sent.time

    # a clear it may not give (allow_estop_clear is off): refused by the robot, and said
    clear = view.send(FID, clear=True)
    view.until(lambda: FID in clear.robot_said, "the robot's word on the clear")
    assert clear.summary().endswith(f"{FID} refused: allow_estop_clear is false")
    assert all(robot.units[u].estop for u in UNITS)

    # kill -9: the broker's last will, at once (the kernel closes the socket)
    os.kill(pid, signal.SIGKILL)
    killed = time.monotonic()
    view.until(lambda: robot.state == "connection_broken", "connection broken", 5)
    assert time.monotonic() - killed <= 1.5 * KEEPALIVE_S + 0.5
    assert not any(model.live(robot, robot.units[u], time.time()) for u in UNITS)
    assert "CONNECTION BROKEN" in view.text()
