"""The ``mqtt`` plugin against a real Mosquitto (tests/support/mosquitto.py: ACLs, users,
TLS with a CA of the test's own), supervisors as ``abh3 run --headless`` processes on the
simulator, and real paho clients as the fleet and an observer. Every payload any test
client receives is validated against the contract's schemas and VDA 5050's
(tests/support/mqtt_watch.py); each test ends by asserting none failed."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from abh3_supervisor.fleet import payloads
from abh3_supervisor.fleet.topics import Topics
from tests.support.mosquitto import FLEET, OBSERVER, Broker, running
from tests.support.mqtt_watch import Received, Watcher, config, supervisor

pytestmark = pytest.mark.wallclock
Match = Callable[[Received], bool]
KEEP = 1  # [s] the frozen supervisor's keep-alive
ROBOTS = {f"sup{i}": [f"sup{i}-rover"] for i in range(1, 13)}


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Broker]:
    with running(tmp_path_factory.mktemp("broker"), ROBOTS) as b:
        yield b


def watch(broker: Broker, user: str = FLEET, **kw: object) -> Watcher:
    w = Watcher(broker, user, client_id=f"t-{user}-{time.monotonic_ns()}", **kw)  # type: ignore[arg-type]
    assert w.connected(), w.refused
    w.subscribe("abh3/v1/#")
    w.subscribe("uagv/v2/#")
    return w


def status(state: str, fid: str) -> Match:
    return lambda m: m.topic == f"abh3/v1/{fid}/status" and m.body["state"] == state


def event(kind: str, fid: str, text: str = "") -> Match:
    return lambda m: (
        m.topic == f"abh3/v1/{fid}/events" and m.body["kind"] == kind and text in m.body["text"]
    )


def estop_state(fid: str, latched: bool) -> Match:
    return lambda m: m.topic == f"abh3/v1/{fid}/units/front/state" and m.body["estop"] is latched


def command(number: int, **over: object) -> dict[str, object]:
    body = payloads.estop_command(number, time.time(), sender="test-fleet", reason="test")
    return {**body, **over}


def test_birth_states_health_and_the_orderly_death_are_retained_and_valid(
    broker: Broker, tmp_path: Path
) -> None:
    w = watch(broker, OBSERVER)
    fid = "sup1-rover"
    with supervisor(config(tmp_path, "sup1", broker, health_s=0.5)) as run:
        w.wait_for(status("online", fid), 30)
        for unit in ("front", "rear"):
            topic = f"abh3/v1/{fid}/units/{unit}/state"
            state = w.wait_for(
                lambda m: (
                    m.topic == topic  # noqa: B023 (waited for here)
                    and m.body["online"] is True
                    and m.body["servo"] == [True, True]
                )
            )
            assert state.body["estop"] is False and state.body["verify"] == "ok"
        health = w.wait_for(
            lambda m: (
                m.topic == f"abh3/v1/{fid}/health"
                and m.body["buses"]["robot"]["frames_received"] > 0
            )
        ).body
        assert health["buses"]["robot"]["frames_sent"] > 0
        assert health["buses"]["robot"]["state"] == "ok"
        assert health["mqtt"]["dropped"] == 0
        w.wait_for(lambda m: m.topic.endswith(f"{fid}/connection"))
        late = watch(broker, OBSERVER)  # a reader who comes later: the retained messages
        born = late.wait_for(status("online", fid))
        assert born.retain and born.body["units"] == ["front", "rear"]
        assert late.wait_for(lambda m: m.topic.endswith("/units/rear/state")).retain
        conn = late.wait_for(lambda m: m.topic.endswith(f"{fid}/connection")).body
        assert conn["connectionState"] == "ONLINE" and conn["serialNumber"] == fid
        seqs = [m.body["seq"] for m in w.messages if m.topic.endswith("/units/front/state")]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert run.proc.returncode == 0, run.log()
    w.wait_for(status("offline", fid))
    topics = [m.topic for m in w.messages]
    offline = max(i for i, m in enumerate(w.messages) if m.body.get("state") == "offline")
    for unit in ("front", "rear"):  # the last word on each unit, then offline
        last = max(i for i, topic in enumerate(topics) if topic.endswith(f"/{unit}/state"))
        assert last < offline
    w.wait_for(lambda m: m.topic.endswith("/connection") and m.body["connectionState"] == "OFFLINE")
    assert not w.wait_for(status("offline", fid)).retain  # live, and retained for later:
    after = watch(broker, OBSERVER)
    assert after.wait_for(status("offline", fid)).retain
    assert "pw-sup1" not in run.log()  # the password, from its file: never logged
    assert not (w.invalid + late.invalid + after.invalid)


def test_kill_9_shows_connection_broken_within_the_keep_alive(
    broker: Broker, tmp_path: Path
) -> None:
    w = watch(broker, OBSERVER)
    fid = "sup2-rover"
    with supervisor(config(tmp_path, "sup2", broker, keepalive_s=1)) as run:
        w.wait_for(status("online", fid), 30)
        w.wait_for(lambda m: m.topic.endswith(f"{fid}/connection"))
        os.kill(run.proc.pid, signal.SIGKILL)
        killed = time.monotonic()
        broken = w.wait_for(status("connection_broken", fid), 10)
        vda = w.wait_for(
            lambda m: (
                m.topic.endswith(f"{fid}/connection")
                and m.body["connectionState"] == "CONNECTIONBROKEN"
            )
        )
        # the broker gives up after 1.5 keep-alives without a packet
        assert broken.at - killed <= 1.5 * 1 + 0.5
        assert vda.at - killed <= 1.5 * 1 + 0.5
        run.proc.wait(5)
    assert not w.invalid


def test_a_frozen_supervisor_shows_connection_broken_within_the_keep_alive_then_returns(
    broker: Broker, tmp_path: Path
) -> None:
    """SIGSTOP: the connection stays open but says nothing, as a host whose network went;
    the broker gives up after 1.5 keep-alives. SIGCONT: paho finds out and reconnects."""
    w = watch(broker, OBSERVER)
    fid = "sup12-rover"
    with supervisor(config(tmp_path, "sup12", broker, keepalive_s=KEEP)) as run:
        w.wait_for(status("online", fid), 30)
        os.kill(run.proc.pid, signal.SIGSTOP)
        stopped = time.monotonic()
        try:
            broken = w.wait_for(status("connection_broken", fid), 1.5 * KEEP + 10)
            # 1.5 keep-alives, and Mosquitto 2.0.11's own checking on top: up to ~5 s
            # (measured: keep-alive 1 → 5.7 s, 4 → 10.9 s, 8 → 16.8 s)
            assert broken.at - stopped <= 1.5 * KEEP + 5.5
        finally:
            mark = w.mark()
            os.kill(run.proc.pid, signal.SIGCONT)
        w.wait_for(status("online", fid), 15, since=mark)
    assert run.proc.returncode == 0, run.log()
    assert not w.invalid


def test_e_stop_needs_the_right_and_the_acl(broker: Broker, tmp_path: Path) -> None:
    fleet, observer = watch(broker), watch(broker, OBSERVER)
    fid, t = "sup3-rover", Topics("sup3-rover")
    with supervisor(config(tmp_path, "sup3", broker)) as run:  # allow_estop: false
        fleet.wait_for(status("online", fid), 30)
        fleet.publish(t.command("estop"), command(1))
        refused = fleet.wait_for(event("fleet_command_refused", fid, "allow_estop is false"))
        assert refused.body["data"]["sender"] is None  # no MQTT 5 property: the payload says
        mark = fleet.mark()
        observer.publish(t.command("estop"), command(2))  # the ACL: an observer only reads
        fleet.publish(t.command("estop_clear"), command(3))  # to know the first went nowhere
        fleet.wait_for(event("fleet_command_refused", fid, "allow_estop_clear"), since=mark)
        assert not [m for m in fleet.messages[mark:] if "seq 2" in str(m.body)]
        assert (
            fleet.wait_for(lambda m: m.topic.endswith("front/state"), since=mark).body["estop"]
            is False
        )
    assert "EMERGENCY STOP" not in run.log()
    assert not (fleet.invalid + observer.invalid)


def test_a_fleet_e_stop_latches_through_the_gate_audited_and_clears_only_when_allowed(
    broker: Broker, tmp_path: Path
) -> None:
    fleet = watch(broker)
    fid, t = "sup4-rover", Topics("sup4-rover")
    with supervisor(config(tmp_path, "sup4", broker, allow_estop=True)) as run:
        fleet.wait_for(status("online", fid), 30)
        fleet.wait_for(
            lambda m: m.topic.endswith("front/state") and m.body["servo"] == [True, True]
        )
        fleet.publish(t.command("estop", everyone=True), command(1), sender="plant-scada")
        latched = fleet.wait_for(event("estop_latched", fid))
        assert "plant-scada" in latched.body["data"]["source"]
        accepted = fleet.wait_for(event("fleet_command", fid))
        assert accepted.body["data"]["sender"] == "plant-scada"
        assert accepted.body["data"]["payload_sender"] == "test-fleet"
        fleet.wait_for(estop_state(fid, True))
        fleet.wait_for(
            lambda m: m.topic.endswith("front/state") and m.body["start"] == [False, False]
        )
        fleet.publish(t.command("estop_clear"), command(1))  # not allowed: still latched
        fleet.wait_for(event("fleet_command_refused", fid, "allow_estop_clear is false"))
    log = run.log()
    assert "operator (plugin mqtt): emergency stop: fleet e-stop by plant-scada" in log, log
    assert "emergency stop cleared" not in log
    with supervisor(
        config(tmp_path, "sup4", broker, allow_estop=True, allow_estop_clear=True)
    ) as run:
        mark = fleet.mark()
        fleet.wait_for(status("online", fid), 30, since=mark)
        fleet.publish(t.command("estop"), command(5))
        fleet.wait_for(estop_state(fid, True), since=mark)
        fleet.publish(t.command("estop_clear"), command(6))
        cleared = fleet.wait_for(event("estop_cleared", fid), since=mark)
        assert "test-fleet" in cleared.body["data"]["source"]
        fleet.wait_for(estop_state(fid, False), since=fleet.mark())
    assert "clear the emergency stop: fleet e-stop clear by test-fleet" in run.log()
    assert not fleet.invalid


def test_retained_stale_future_malformed_and_repeated_commands_are_refused(
    broker: Broker, tmp_path: Path
) -> None:
    fleet = watch(broker)
    fid, t = "sup5-rover", Topics("sup5-rover")
    # a retained e-stop, fresh when the supervisor connects: the broker replays it
    fleet.publish(t.command("estop"), command(1), retain=True)
    cfg = config(tmp_path, "sup5", broker, allow_estop=True, command_timeout_ms=5000)
    with supervisor(cfg) as run:
        fleet.wait_for(status("online", fid), 30)
        fleet.wait_for(event("fleet_command_refused", fid, "retained"))
        mark = fleet.mark()
        fleet.publish(t.command("estop"), b"", retain=True)  # the retained one, deleted
        fleet.wait_for(event("fleet_command_refused", fid, "retained"), since=mark)
        # published retained while the robot listens: MQTT 5's "retain as published" keeps
        # the flag on the live copy too, so it is refused as well
        mark = fleet.mark()
        fleet.publish(t.command("estop"), command(2), retain=True)
        fleet.wait_for(event("fleet_command_refused", fid, "retained"), since=mark)
        fleet.publish(t.command("estop"), b"", retain=True)
        now = time.time()
        cases = {
            "stale": command(2, time=now - 6),
            "from the future": command(3, time=now + 6),
            "not JSON": b"{estop",
            "'reason': missing": {k: v for k, v in command(4).items() if k != "reason"},
            "'v': 2": command(5, v=2),
            "'seq': str": command(6, seq="7"),
        }
        for why, body in cases.items():
            mark = fleet.mark()
            fleet.publish(t.command("estop"), body)
            fleet.wait_for(event("fleet_command_refused", fid, why), since=mark)
        fleet.wait_for(lambda m: m.topic.endswith("front/state") and m.body["estop"] is False)
        # 10 MB, a valid e-stop but for its size: MQTT 5 told the broker our maximum packet
        # size, so it never arrives (under 3.1.1 it is refused unread: test_fleet_contract)
        fleet.publish(t.command("estop"), command(9, reason="x" * 10_000_000))
        fleet.publish(t.command("estop"), command(10))
        fleet.wait_for(event("estop_latched", fid))
        obeyed = fleet.wait_for(event("fleet_command", fid)).body["data"]
        assert obeyed["seq"] == 10
        # refusals are told at most 10 a second (the rest counted into one later event),
        # and ten came within about half a second: the repeat goes in a second of its own,
        # as the robot's own clock shows it
        said = [m for m in fleet.messages if event("fleet_command_refused", fid)(m)]
        quiet = said[-1].body["time"] + 1.1
        fleet.wait_for(
            lambda m: m.topic.startswith(f"abh3/v1/{fid}/units/") and m.body["time"] > quiet
        )
        mark = fleet.mark()
        fleet.publish(t.command("estop"), command(10))  # the same seq again
        fleet.wait_for(event("fleet_command_refused", fid, "seq 10 not above 10"), since=mark)
    assert run.log().count("EMERGENCY STOP (") == 1
    # what we sent malformed on purpose fails the command schemas too; nothing else did
    assert len([i for i in fleet.invalid if "/cmd/estop:" in i]) == 3
    assert not [i for i in fleet.invalid if "/cmd/" not in i]


def test_vda5050_start_pause_and_stop_pause(broker: Broker, tmp_path: Path) -> None:
    fleet = watch(broker)
    fid, t = "sup6-rover", Topics("sup6-rover")
    cfg = config(tmp_path, "sup6", broker, allow_estop=True)
    with supervisor(cfg):
        fleet.wait_for(status("online", fid), 30)
        online = fleet.wait_for(lambda m: m.topic == t.connection)
        assert online.body["connectionState"] == "ONLINE"

        def actions(header: int, *kinds: str) -> dict[str, object]:
            return payloads.vda_instant_actions(
                header, time.time(), manufacturer=t.manufacturer, fleet_id=fid, actions=[*kinds]
            )

        fleet.publish(t.instant_actions, actions(1, "startPause"))
        fleet.wait_for(event("estop_latched", fid))
        fleet.wait_for(estop_state(fid, True))
        fleet.publish(t.instant_actions, actions(2, "stopPause", "pick"))
        fleet.wait_for(event("fleet_command_refused", fid, "pick"))
        fleet.wait_for(event("fleet_command_refused", fid, "allow_estop_clear is false"))
        wrong = {**actions(3, "startPause"), "serialNumber": "someone-else"}
        fleet.publish(t.instant_actions, wrong)
        fleet.wait_for(event("fleet_command_refused", fid, "serialNumber"))
    sent = [m for m in fleet.messages if m.topic == t.instant_actions]
    assert len(sent) == 3  # ours too, validated against the official schema on receipt
    assert not fleet.invalid


def test_each_action_of_a_vda5050_message_is_judged_on_its_own_and_malformed_is_refused(
    broker: Broker, tmp_path: Path
) -> None:
    fleet = watch(broker)
    fid, t = "sup10-rover", Topics("sup10-rover")
    with supervisor(config(tmp_path, "sup10", broker, allow_estop=True)) as run:
        fleet.wait_for(status("online", fid), 30)
        actions = payloads.vda_instant_actions(
            1, time.time(), manufacturer=t.manufacturer, fleet_id=fid,
            actions=["stopPause", "startPause"],
        )  # fmt: skip
        fleet.publish(t.instant_actions, actions)  # the clear not allowed, the stop is
        fleet.wait_for(event("fleet_command_refused", fid, "allow_estop_clear is false"))
        fleet.wait_for(event("estop_latched", fid))
        fleet.wait_for(estop_state(fid, True))
        for why, body in {
            "malformed: RecursionError": b"[" * 2040 + b"]" * 2040,
            "malformed: OverflowError": command(2, time=10**400),
        }.items():
            mark = fleet.mark()
            fleet.publish(t.command("estop"), body)
            fleet.wait_for(event("fleet_command_refused", fid, why), since=mark)
    assert "could not be handled" not in run.log()


def test_a_flood_of_twists_never_holds_an_e_stop_back(broker: Broker, tmp_path: Path) -> None:
    """Twists are read at most 100 a second on their connection; e-stops have their own,
    and what the robot says goes out on a third that reads nothing. The flood comes from a
    client of its own: queued behind 3000 messages on the test's own connection, the e-stop
    would be held back by the test, not by the supervisor; and the test listens to the
    robot's status and events only: subscribed to the twists too, its own client would
    read (and check against the schema) the whole flood before the event, seconds on a
    busy machine, and the test would time itself. The e-stop comes sixty refusal events
    (4–6 s) into the flood: the broker's acknowledgements of the robot's events were once read behind the unread twists, and
    after paho's 20 unacknowledged the robot fell silent — its e-stop event too."""
    fid, t = "sup11-rover", Topics("sup11-rover")
    fleet = Watcher(broker, FLEET, client_id=f"t-{FLEET}-{time.monotonic_ns()}")
    assert fleet.connected(), fleet.refused
    for topic in (f"abh3/v1/{fid}/status", f"abh3/v1/{fid}/events"):
        fleet.subscribe(topic)
    flooder = Watcher(broker, FLEET, client_id=f"t-flood-{time.monotonic_ns()}")
    assert flooder.connected(), flooder.refused
    with supervisor(config(tmp_path, "sup11", broker, allow_estop=True)):
        fleet.wait_for(status("online", fid), 30)
        body = payloads.twist_command(1, time.time(), sender="flood", linear=0.0, angular=0.0)
        twist = payloads.encode(body)
        for _ in range(3000):  # 30 s of reading at the cap, queued at the broker
            flooder.client.publish(t.command("twist"), twist, 0)
        first = fleet.wait_for(event("fleet_command_refused", fid), timeout=10)  # being read
        sixty = first.body["seq"] + 60  # refusals are said at most 10 a second
        fleet.wait_for(lambda m: event("fleet_command_refused", fid)(m) and m.body["seq"] >= sixty)
        mark = fleet.mark()
        fleet.publish(t.command("estop"), command(1))
        fleet.wait_for(event("estop_latched", fid), timeout=5, since=mark)
    flooder.close()


def _speed(m: Received) -> float:
    measured = m.body["measured"]
    return float(max(abs(measured["a"] or 0.0), abs(measured["b"] or 0.0)))


def test_a_fleet_twist_owns_the_robot_while_it_keeps_coming_and_zero_after_the_timeout(
    broker: Broker, tmp_path: Path
) -> None:
    fleet = watch(broker)
    fid, t = "sup7-rover", Topics("sup7-rover")
    cfg = config(tmp_path, "sup7", broker, allow_commands=True, command_timeout_ms=300)
    with supervisor(cfg):
        fleet.wait_for(status("online", fid), 30)
        fleet.wait_for(
            lambda m: m.topic.endswith("front/state") and m.body["start"] == [True, True]
        )
        source = f"mqtt:{fid}"
        seq, moving = 0, None
        deadline = time.monotonic() + 10
        while moving is None and time.monotonic() < deadline:  # a command every 0.1 s
            seq += 1
            body = payloads.twist_command(
                seq, time.time(), sender="test-fleet", linear=0.2, angular=0.0
            )
            mark = fleet.mark()
            fleet.publish(t.command("twist"), body)
            try:
                moving = fleet.wait_for(
                    lambda m: (
                        m.topic.endswith("front/state")
                        and m.body["owner"] == source
                        and _speed(m) > 100
                    ),
                    0.1,
                    since=mark,
                )
            except AssertionError:
                continue
        assert moving is not None, "the drive never moved on the fleet's twist"
        stopped_at = time.monotonic()
        idle = fleet.wait_for(
            lambda m: (
                m.topic.endswith("front/state")
                and m.body["owner"] is None
                and m.body["commanded"] == {"ay": 0.0, "bx": 0.0}
                and _speed(m) < 5
            ),
            5,
            since=fleet.mark(),
        )
        # silence → zero after command_timeout_ms, then the motors' lag
        assert idle.at - stopped_at < 0.3 + 1.5
        fleet.wait_for(event("owner", fid, f"{source} → nobody"))
    assert not fleet.invalid


def test_tls_with_a_client_certificate_and_mqtt_3_1_1(broker: Broker, tmp_path: Path) -> None:
    w = watch(broker, OBSERVER, tls=True)  # the observer over TLS too
    fid = "sup8-rover"
    tls = {
        "ca": broker.certs("ca.crt"),
        "cert": broker.certs("client.crt"),
        "key": broker.certs("client.key"),
    }
    cfg = config(tmp_path, "sup8", broker, broker=broker.tls_url, tls=tls, protocol="3.1.1")
    with supervisor(cfg) as run:
        w.wait_for(status("online", fid), 30)
        w.wait_for(lambda m: m.topic.endswith(f"{fid}/units/front/state"))
    assert run.proc.returncode == 0
    assert not w.invalid


def test_a_wrong_password_is_said_without_the_password(broker: Broker, tmp_path: Path) -> None:
    cfg = config(tmp_path, "sup9", broker)
    (tmp_path / "sup9.password").write_text("not-the-password\n")
    with supervisor(cfg) as run:
        deadline = time.monotonic() + 20
        while "refused the connection" not in run.log() and time.monotonic() < deadline:
            time.sleep(0.05)  # polling the log file: the only thing the process says
    log = run.log()
    assert "refused the connection" in log and "not-the-password" not in log


@pytest.mark.parametrize("loss", ["continue", "stop"])
def test_losing_the_broker_moves_nothing_or_stops_when_asked_and_reconnects(
    loss: str, tmp_path: Path
) -> None:
    user = f"sup{10 if loss == 'continue' else 11}"
    fid = f"{user}-rover"
    with running(tmp_path / "own-broker", {user: [fid]}) as own:
        with supervisor(config(tmp_path, user, own, on_broker_loss=loss, health_s=0.5)) as run:
            w = watch(own, OBSERVER)
            w.wait_for(status("online", fid), 30)
            own.stop(signal.SIGKILL)
            w.close()
            deadline = time.monotonic() + 10
            while "lost the broker" not in run.log() and time.monotonic() < deadline:
                time.sleep(0.05)  # polling the log file: the only thing the process says
            own.start()
            back = time.monotonic()
            w = watch(own, OBSERVER)
            w.wait_for(status("online", fid), 10)
            assert time.monotonic() - back < 10
            health = w.wait_for(
                lambda m: m.topic.endswith("/health") and m.body["mqtt"]["reconnects"] >= 1
            )
            if loss == "stop":
                w.wait_for(lambda m: m.topic.endswith("front/state") and m.body["estop"])
            else:  # the states of a second after: none says e-stop
                last = w.wait_for(lambda m: m.topic.endswith("front/state") and m.body["seq"] > 20)
                states = [m for m in w.messages if m.topic.endswith("/state")]
                assert last.body["servo"] == [True, True]
                assert not [m for m in states if m.body["estop"]]
            assert health.body["mqtt"]["queued"] >= 0
        log = run.log()
        assert ("EMERGENCY STOP (plugin mqtt: on_broker_loss: stop" in log) is (loss == "stop")
        assert not w.invalid


def test_a_twist_to_a_robot_that_is_not_ready_is_refused_in_its_event_naming_the_drive(
    broker: Broker, tmp_path: Path
) -> None:
    """The robot decision said in MQTT's own answer (docs/safety.md): after an e-stop and
    its clear the drives are switched off, so a fleet twist is refused, naming the drive,
    in a fleet_command_refused event rather than only in the robot's own log."""
    fleet = watch(broker)
    fid, t = "sup8-rover", Topics("sup8-rover")
    cfg = config(
        tmp_path, "sup8", broker, allow_commands=True, allow_estop=True, allow_estop_clear=True
    )
    with supervisor(cfg):
        mark = fleet.mark()
        fleet.wait_for(status("online", fid), 30, since=mark)
        fleet.publish(t.command("estop"), command(1))
        fleet.wait_for(estop_state(fid, True), since=mark)
        fleet.publish(t.command("estop_clear"), command(2))
        fleet.wait_for(estop_state(fid, False), since=fleet.mark())
        mark = fleet.mark()
        body = payloads.twist_command(3, time.time(), sender="test-fleet", linear=0.2, angular=0)
        fleet.publish(t.command("twist"), body)
        refused = fleet.wait_for(event("fleet_command_refused", fid, "may not move"), since=mark)
        assert "front: SERVO A" in refused.body["text"] or "rear: SERVO A" in refused.body["text"]
    assert not fleet.invalid
