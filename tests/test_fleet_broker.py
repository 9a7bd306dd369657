"""``abh3 fleet`` against the suite's real Mosquitto on 127.0.0.1 (tests/support/mosquitto.py:
a generated configuration, users, ACLs, a TLS CA): a hand-made publisher (paho) plays two robots; the fleet's client
sees them, its e-stop-all reaches the robots' subscription, a user without the right is
refused by the broker and told so, a robot whose connection dies shows its last will, and
what a user gets wrong (URL, credentials, TLS, the broker gone) is said, exit 1 or 2.
Skipped, with the reason, where Mosquitto or paho-mqtt is not installed."""

from __future__ import annotations

import asyncio
import fcntl
import json
import os
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients.fleet.app import FleetApp
from abh3_supervisor.clients.fleet.broker import BrokerOptions, FleetClient
from abh3_supervisor.clients.fleet.commands import Commander
from abh3_supervisor.clients.fleet.model import FleetModel
from tests.support import mosquitto
from tests.support.fleet_payloads import PREFIX, state_topic, status, status_topic, unit_state
from tests.support.mosquitto import FLEET, OBSERVER, Broker, free_port, password
from tests.support.terminal import ended, spawn

mqtt = pytest.importorskip("paho.mqtt.client", reason="paho-mqtt: pip install -e '.[mqtt]'")
pytestmark = pytest.mark.wallclock
ROBOTS = ("plant-a", "plant-b")
MANY = tuple(f"agv-{n:02d}" for n in range(20))
UNITS = ("left", "right")
ROBOT_USER = "robot"  # the hand-made robots' user: it may speak for ROBOTS and MANY
DEADLINE_S = 10.0


def wait_for(condition: Callable[[], object], what: str, timeout: float = DEADLINE_S) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        time.sleep(0.01)


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    """The suite's Mosquitto (tests/support/mosquitto.py): its users, ACL and TLS CA."""
    with mosquitto.running(tmp_path / "broker", {ROBOT_USER: [*ROBOTS, *MANY]}) as running:
        yield running


@dataclass
class Robot:
    """One robot as the mqtt plugin would be: its own connection, its last will, retained
    status and unit states, a subscription to its commands."""

    fid: str
    client: Any
    commands: list[tuple[str, dict[str, Any], list[tuple[str, str]]]] = field(default_factory=list)

    def publish_units(self, **fields: Any) -> None:
        for n, unit in enumerate(UNITS):
            payload = unit_state(self.fid, unit, time=time.time(), seq=n + 1, **fields)
            self.client.publish(state_topic(self.fid, unit), payload, qos=0, retain=True)


def robot(port: int, fid: str) -> Robot:
    from paho.mqtt.enums import CallbackAPIVersion

    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"abh3-{fid}", protocol=mqtt.MQTTv5)
    client.username_pw_set(ROBOT_USER, password(ROBOT_USER))
    will = status(fid, "connection_broken", time=time.time())
    client.will_set(status_topic(fid), will, qos=1, retain=True)
    me = Robot(fid, client)
    subscribed: list[int] = []

    def on_message(c: Any, u: Any, message: Any) -> None:
        props = getattr(message.properties, "UserProperty", [])
        me.commands.append((message.topic, json.loads(message.payload), props))

    def on_connect(c: Any, u: Any, flags: Any, rc: Any, props: Any) -> None:
        """As the plugin does: (again) its subscriptions, its status, its units' state."""
        c.subscribe([(f"{PREFIX}/{fid}/cmd/#", 1), (f"{PREFIX}/all/cmd/#", 1)])
        c.publish(status_topic(fid), status(fid, time=time.time()), qos=1, retain=True)
        me.publish_units()

    client.on_connect = on_connect
    client.on_message = on_message
    client.on_subscribe = lambda c, u, mid, codes, props: subscribed.append(mid)
    client.connect("127.0.0.1", port, keepalive=10)
    client.reconnect_delay_set(0.1, 1)
    client.loop_start()
    wait_for(lambda: subscribed, f"{fid} subscribed")
    return me


@pytest.fixture
def robots(broker: Broker) -> Iterator[dict[str, Robot]]:
    them = {fid: robot(broker.port, fid) for fid in ROBOTS}
    yield them
    for r in them.values():
        r.client.disconnect()
        r.client.loop_stop()


def fleet_client(port: int, user: str, protocol: str = "5") -> FleetClient:
    opts = BrokerOptions(
        "127.0.0.1",
        port,
        tls=False,
        protocol=protocol,
        username=user,
        password=password(user),
        client_id=f"abh3-fleet-{user}-test",
    )
    client = FleetClient(opts, PREFIX)
    client.connect(timeout=DEADLINE_S)
    return client


def seen_all(model: FleetModel, client: FleetClient, now: float) -> bool:
    for message in client.drain():
        model.feed(message.topic, message.payload, message.retained, message.time)
    return all(
        fid in model.robots
        and model.robots[fid].online
        and all(u in model.robots[fid].units for u in UNITS)
        for fid in ROBOTS
    )


def test_the_fleet_sees_both_robots_and_its_e_stop_all_reaches_them(
    broker: Broker, robots: dict[str, Robot]
) -> None:
    client = fleet_client(broker.port, FLEET)
    model = FleetModel(PREFIX)
    try:
        wait_for(lambda: seen_all(model, client, time.time()), "both robots and their units")
        asyncio.run(_e_stop_all_from_the_view(client, model, robots))
    finally:
        client.close()


async def _e_stop_all_from_the_view(
    client: FleetClient, model: FleetModel, robots: dict[str, Robot]
) -> None:
    app = FleetApp(model, Commander(client.options.client_id, PREFIX), client, "e2e")
    async with app.run_test(size=(150, 40)) as pilot:
        await pilot.press("E", "y")
        await _until(pilot, lambda: all(r.commands for r in robots.values()), "e-stop at both")
        for r in robots.values():
            topic, body, props = r.commands[0]
            assert topic == f"{PREFIX}/all/cmd/estop"
            assert (body["v"], body["seq"], body["sender"], body["reason"]) == (
                1,
                1,
                "abh3-fleet-fleet-test",
                "e2e",
            )
            assert ("sender", "abh3-fleet-fleet-test") in props  # MQTT 5's user property
        latest = app.session.commander.latest()
        assert latest is not None
        await _until(pilot, lambda: "taken by the broker" in latest.summary(), "the PUBACK")
        for r in robots.values():  # the robots obey: their state says so
            r.publish_units(estop=True)
        await _until(pilot, lambda: "latched on 2 robots" in latest.summary(), "both latched")


async def _until(pilot: Any, condition: Callable[[], object], what: str) -> None:
    deadline = time.monotonic() + DEADLINE_S
    while not condition():
        assert time.monotonic() < deadline, f"not within {DEADLINE_S} s: {what}"
        await pilot.pause(0.02)


@pytest.mark.parametrize("protocol", ["5", "3.1.1"])
def test_a_user_without_the_right_is_refused_by_the_broker_and_told(
    broker: Broker, robots: dict[str, Robot], protocol: str
) -> None:
    client = fleet_client(broker.port, OBSERVER, protocol)
    model = FleetModel(PREFIX)
    commander = Commander(client.options.client_id, PREFIX, v5=protocol == "5")
    try:
        wait_for(lambda: seen_all(model, client, time.time()), "both robots")
        sent = commander.build(model, "plant-a", clear=False, reason="r", now=time.time())
        _, trouble = client.publish(sent.topic, sent.payload)
        assert trouble is None
        acks: list[tuple[int, int, str]] = []

        def acked() -> bool:
            acks.extend(client.take_acks())
            return bool(acks)

        wait_for(acked, "the PUBACK")
        commander.acknowledged(sent, acks[0][1], acks[0][2])
        if protocol == "5":
            assert "REFUSED by the broker: Not authorized (0x87)" in sent.summary()
        else:  # 3.1.1 has no way to say it: never claimed as taken
            assert sent.summary().endswith("sent, not confirmed; no word yet from plant-a")
        assert robots["plant-a"].commands == []
    finally:
        client.close()


def test_a_robot_whose_connection_dies_shows_its_last_will(
    broker: Broker, robots: dict[str, Robot]
) -> None:
    client = fleet_client(broker.port, FLEET)
    model = FleetModel(PREFIX)
    try:
        wait_for(lambda: seen_all(model, client, time.time()), "both robots")
        dying = robots["plant-b"].client
        dying.loop_stop()
        dying.socket().close()  # no DISCONNECT: the broker publishes the will
        wait_for(
            lambda: (
                seen_all(model, client, time.time())
                or model.robots["plant-b"].state == "connection_broken"
            ),
            "plant-b's last will",
        )
        assert model.robots["plant-a"].online
        dead = model.robots["plant-b"]
        assert not model.live(dead, dead.units["left"], time.time())
    finally:
        client.close()


def test_a_broker_restart_is_said_and_the_view_comes_back_with_the_robots(
    broker: Broker, robots: dict[str, Robot]
) -> None:
    client = fleet_client(broker.port, FLEET)
    model = FleetModel(PREFIX)
    try:
        wait_for(lambda: seen_all(model, client, time.time()), "both robots")
        before = model.robots["plant-a"].status_time
        broker.stop()
        wait_for(lambda: not client.connected, "the loss noticed")
        assert "LOST" in client.describe(time.time())
        broker.start()  # empty (no persistence): the robots publish again on reconnecting
        wait_for(lambda: client.connected, "reconnected", timeout=15)
        assert client.reconnects == 1 and "LOST" not in client.describe(time.time())
        wait_for(
            lambda: (
                seen_all(model, client, time.time())
                and model.robots["plant-a"].status_time > before
            ),
            "the robots' status again, through the new subscription",
        )
    finally:
        client.close()


def test_twenty_robots_of_two_units_are_all_shown_live_within_2_s(broker: Broker) -> None:
    """The view's half of issue 33's scale check: 40 units through one broker. Their
    retained state arrives with the subscription (shown, greyed: not seen live); the
    next state each robot publishes (2 Hz in the plugin, once here) makes it live."""
    fleet_ids = list(MANY)
    many = [robot(broker.port, fid) for fid in fleet_ids]
    try:
        client = fleet_client(broker.port, FLEET)
        model = FleetModel(PREFIX)

        def shown() -> bool:
            for m in client.drain():
                model.feed(m.topic, m.payload, m.retained, m.time)
            return sum(len(model.robots[f].units) for f in fleet_ids if f in model.robots) == 40

        wait_for(shown, "40 units shown", timeout=2.0)
        for r in many:
            r.publish_units()

        def live() -> bool:
            shown()
            now = time.time()
            return all(model.live(model.robots[f], u, now) for f in fleet_ids for u in model.robots[f].units.values())  # fmt: skip

        wait_for(live, "40 units live", timeout=2.0)
        client.close()
    finally:
        for r in many:
            r.client.disconnect()
            r.client.loop_stop()


def test_a_10_mb_message_is_counted_as_malformed_and_nothing_else_changes(
    broker: Broker, robots: dict[str, Robot]
) -> None:
    client = fleet_client(broker.port, FLEET)
    model = FleetModel(PREFIX)
    try:
        wait_for(lambda: seen_all(model, client, time.time()), "both robots")
        robots["plant-a"].client.publish(state_topic("plant-a", "left"), b"{" * 10_000_000, qos=1)
        wait_for(lambda: seen_all(model, client, time.time()) and model.malformed, "counted")
        assert "larger than any payload" in model.problem
        assert model.robots["plant-a"].units["left"].verify == "ok"  # what was shown stays
    finally:
        client.close()


def abh3_fleet(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "fleet", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, **(env or {})},
        stdin=subprocess.DEVNULL,
    )


def test_what_a_user_gets_wrong_is_said_without_a_traceback(broker: Broker, tmp_path: Path) -> None:
    url = f"mqtt://127.0.0.1:{broker.port}"
    secret = tmp_path / "pw"
    secret.write_text("wrong-password\n")
    cases = [
        (["--broker", "http://127.0.0.1"], 2, "not mqtt://host:1883"),
        (["--broker", "mqtt://127.0.0.1:99999"], 2, "--broker"),
        (["--broker", url, "--password-env", "NO_SUCH_VAR_X"], 2, "the environment has no"),
        (["--broker", url, "--username", "u", "--ca", "/nonexistent"], 2, "need an mqtts://"),
        (
            ["--broker", url, "--username", FLEET, "--password-file", str(secret)],
            1,
            "refused the connection",
        ),
        (["--broker", f"mqtts://127.0.0.1:{broker.port}"], 1, "TLS failure"),  # plain port
        (
            ["--broker", f"mqtts://127.0.0.1:{broker.tls_server_port}"],
            1,
            "certificate verify failed",
        ),
        (["--broker", f"mqtt://127.0.0.1:{free_port()}"], 1, "unreachable"),
    ]
    for args, code, said in cases:
        out = abh3_fleet(*args)
        assert (out.returncode, out.stdout) == (code, ""), (args, out.stderr)
        assert said in out.stderr and "Traceback" not in out.stderr, (args, out.stderr)
        assert "wrong-password" not in out.stderr
    as_fleet = ["--username", FLEET, "--password-env", "FLEET_PW"]
    env_case = abh3_fleet("--broker", url, *as_fleet, env={"FLEET_PW": "bad-pw-xyz"})
    assert env_case.returncode == 1 and "bad-pw-xyz" not in env_case.stderr
    # the right credentials connect; then it wants a terminal (here there is none)
    right = {"FLEET_PW": password(FLEET)}
    good = abh3_fleet("--broker", url, *as_fleet, env=right)
    assert good.returncode == 1 and "not a terminal" in good.stderr, good.stderr
    assert password(FLEET) not in good.stderr
    ca = broker.certs("ca.crt")
    tls_url = f"mqtts://127.0.0.1:{broker.tls_server_port}"
    tls = abh3_fleet("--broker", tls_url, "--ca", ca, *as_fleet, env=right)
    assert tls.returncode == 1 and "not a terminal" in tls.stderr, tls.stderr  # TLS: through
    mutual = ["--broker", broker.tls_url, "--ca", ca]
    no_cert = abh3_fleet(*mutual, *as_fleet, env=right)
    assert no_cert.returncode == 1 and "TLS failure" in no_cert.stderr, no_cert.stderr
    pair = ["--cert", broker.certs("client.crt"), "--key", broker.certs("client.key")]
    with_cert = abh3_fleet(*mutual, *pair, *as_fleet, env=right)
    assert with_cert.returncode == 1 and "not a terminal" in with_cert.stderr, with_cert.stderr


def read_until(fd: int, wanted: Callable[[bytes], bool], what: str) -> bytes:
    screen = b""
    deadline = time.monotonic() + 30
    while not wanted(screen):
        assert time.monotonic() < deadline, f"not on the screen: {what}: {screen[-800:]!r}"
        ready, _, _ = select.select([fd], [], [], 1)
        if ready:
            screen += os.read(fd, 65536)
    return screen


def test_abh3_fleet_on_a_terminal_shows_the_robots_e_stops_all_attaches_and_quits(
    broker: Broker, robots: dict[str, Robot], tmp_path: Path
) -> None:
    """The whole command on a pseudo-terminal: connect, show, `E` `y`, `a` (the robot's
    TUI run and the view back when it ends), `q` exit 0."""
    unreachable = f"ssh://nobody@127.0.0.1:{free_port()}/nonexistent.sock"  # fails at once
    robots["plant-a"].client.publish(
        status_topic("plant-a"), status("plant-a", time=time.time(), attach=unreachable), 1, True
    )
    secret = tmp_path / "pw"
    secret.write_text(password(FLEET) + "\n")
    url = f"mqtt://127.0.0.1:{broker.port}"
    pid, fd = spawn(["fleet", "--broker", url, "--username", FLEET, "--password-file", str(secret)])  # fmt: skip
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 160, 0, 0))
    try:
        read_until(fd, lambda s: s.count(b"ONLINE") >= 2 and b"attach: a" in s, "both robots")
        os.write(fd, b"E")
        read_until(fd, lambda s: b"E-STOP ALL" in s, "the question")
        os.write(fd, b"y")
        wait_for(lambda: all(r.commands for r in robots.values()), "the e-stop at both robots")
        assert {r.commands[0][0] for r in robots.values()} == {f"{PREFIX}/all/cmd/estop"}
        os.write(fd, b"a")  # plant-a is selected: its TUI cannot reach it and ends with 1
        read_until(fd, lambda s: b"ended with 1" in s, "the view back after the TUI ended")
        os.write(fd, b"q")
        end = ended(pid, fd)
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        raise
    assert end.code == 0, end.screen[-800:]
    assert password(FLEET).encode() not in end.screen


def test_a_signal_ends_abh3_fleet_at_once_with_the_terminal_given_back(
    broker: Broker, robots: dict[str, Robot], tmp_path: Path
) -> None:
    secret = tmp_path / "pw"
    secret.write_text(password(OBSERVER))
    url = f"mqtt://127.0.0.1:{broker.port}"
    pid, fd = spawn(["fleet", "--broker", url, "--username", OBSERVER, "--password-file", str(secret)])  # fmt: skip
    try:
        read_until(fd, lambda s: s.count(b"ONLINE") >= 2, "both robots")
        os.kill(pid, signal.SIGTERM)
        end = ended(pid, fd)
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        raise
    assert end.code == 0, end.screen[-800:]
    assert b"\x1b[?1049l" in end.screen  # the alternate screen left: the terminal is back
