"""``abh3 fleet``'s model, commands and text on hand-made payloads, on a fake clock: every
robot state, ageing, retained copies, malformed payloads; the e-stop payloads and what
is said of them."""

from __future__ import annotations

import json

import pytest

from abh3_supervisor.clients.fleet import reading
from abh3_supervisor.clients.fleet.commands import Commander
from abh3_supervisor.clients.fleet.model import EVENTS_KEPT, FleetModel
from abh3_supervisor.clients.fleet.view import render
from abh3_supervisor.fleet import payloads
from tests.support.fleet_payloads import (
    PREFIX,
    T0,
    event,
    state_topic,
    status,
    status_topic,
    unit_state,
)
from tests.support.mqtt_watch import VALIDATORS

A, B = "plant-a", "plant-b"


def fleet(stale_s: float = 2.0) -> FleetModel:
    return FleetModel(PREFIX, stale_s)


def online(model: FleetModel, fid: str = A, at: float = T0) -> None:
    model.feed(status_topic(fid), status(fid, time=at - 60), True, at)
    for n, unit in enumerate(("left", "right")):
        model.feed(state_topic(fid, unit), unit_state(fid, unit, time=at, seq=n + 1), False, at)


def shown(model: FleetModel, now: float, selected: str | None = A) -> str:
    return render(model, now, selected, "broker: connected", None).plain


def test_a_live_robot_is_online_with_every_field_as_published() -> None:
    model = fleet()
    online(model)
    robot = model.robots[A]
    assert (robot.state, robot.host, robot.pid, robot.declared) == (
        "online",
        "agv-host",
        4242,
        ("left", "right"),
    )
    left = robot.units["left"]
    assert model.live(robot, left, T0 + 1)
    assert (left.online, left.servo, left.start) == (True, (True, True), (True, False))
    assert (left.commanded, left.measured) == ((300.0, 0.0), (298.5, None))
    assert (left.owner, left.estop, left.verify, left.report_age_s) == (
        "tui:operator",
        False,
        "ok",
        0.02,
    )
    text = shown(model, T0 + 1)
    assert "ONLINE" in text and "298.5" in text and "?" in text  # b never measured: "?"
    assert "stale" not in text


def test_the_payloads_these_tests_feed_are_the_contracts() -> None:
    """Built by the plugin's own builders (tests/support/fleet_payloads.py): each one
    validates against its schema, so the view is tested on what the plugin publishes."""
    for name, payload in (
        ("status", status(A, attach="ssh://agv@host/run/abh3.sock")),
        ("status", status(A, "connection_broken")),
        ("unit_state", unit_state(A, "left")),
        ("unit_state", unit_state(A, "left", foreign_host={"address": 5, "frames": 12})),
        ("event", event(A, "fleet_command_refused", "r", data={"sender": None})),
    ):
        VALIDATORS[name].validate(json.loads(payload))


def test_values_age_and_grey_after_stale_s_on_a_fake_clock() -> None:
    model = fleet(stale_s=2.0)
    online(model)
    robot, left = model.robots[A], model.robots[A].units["left"]
    assert model.live(robot, left, T0 + 2.0)
    assert not model.live(robot, left, T0 + 2.01)
    assert model.age(left, T0 + 5) == pytest.approx(5.0)
    text = shown(model, T0 + 5)
    assert "5.0 s (stale)" in text
    # a fresh message makes it live again
    model.feed(state_topic(A, "left"), unit_state(A, "left", time=T0 + 5, seq=9), False, T0 + 5)
    assert model.live(robot, robot.units["left"], T0 + 5.5)


def test_the_last_will_shows_connection_broken_and_nothing_live() -> None:
    model = fleet()
    online(model)
    will = status(A, "connection_broken", time=T0 - 60)  # the will is the birth's copy
    model.feed(status_topic(A), will, False, T0 + 0.5)
    robot = model.robots[A]
    assert robot.state == "connection_broken"
    assert not model.live(robot, robot.units["left"], T0 + 0.6)  # fresh, but its host is gone
    text = shown(model, T0 + 0.6)
    assert "CONNECTION BROKEN" in text and "(robot not online)" in text


def test_an_orderly_offline_robot() -> None:
    model = fleet()
    model.feed(status_topic(B), status(B, "offline"), True, T0)
    text = shown(model, T0 + 1, selected=B)
    assert "offline" in text and "never seen" in text  # its declared units: no state seen
    assert "ONLINE" not in text


def test_a_robot_without_status_is_never_shown_online() -> None:
    model = fleet()
    model.feed(state_topic(A, "left"), unit_state(A, "left"), False, T0)
    robot = model.robots[A]
    assert robot.state is None and not robot.online
    assert not model.live(robot, robot.units["left"], T0)
    assert "no status seen" in shown(model, T0)


def test_a_retained_state_is_shown_as_of_its_own_time_until_a_live_one_comes() -> None:
    model = fleet()
    model.feed(status_topic(A), status(A), True, T0)
    old = unit_state(A, "left", time=T0 - 3600, seq=40)
    model.feed(state_topic(A, "left"), old, True, T0)
    robot = model.robots[A]
    left = robot.units["left"]
    assert not model.live(robot, left, T0) and model.age(left, T0) == pytest.approx(3600)
    assert "retained copy" in shown(model, T0)
    model.feed(state_topic(A, "left"), unit_state(A, "left", time=T0, seq=1), False, T0)
    assert model.live(robot, robot.units["left"], T0)


def test_a_retained_replay_older_than_what_is_shown_is_ignored() -> None:
    """A resubscribe (the broker reconnecting) replays retained copies: never backwards."""
    model = fleet()
    online(model, at=T0)
    stale_copy = unit_state(A, "left", time=T0 - 1, seq=1, estop=True)
    model.feed(state_topic(A, "left"), stale_copy, True, T0 + 0.1)
    robot = model.robots[A]
    assert not robot.units["left"].estop and model.live(robot, robot.units["left"], T0 + 0.2)


def test_the_brokers_status_is_taken_whatever_its_time() -> None:
    """A will is built when its robot connects: older than the birth. Seen retained after
    a resubscribe (the robot died while this view was away), it is the truth."""
    model = fleet()
    online(model, at=T0)
    will = status(A, "connection_broken", time=T0 - 61)
    model.feed(status_topic(A), will, True, T0 + 30)
    assert model.robots[A].state == "connection_broken"


def test_errors_alarms_foreign_host_and_e_stop_by_name() -> None:
    model = fleet()
    model.feed(status_topic(A), status(A), True, T0)
    payload = unit_state(
        A,
        "left",
        errors=["overcurrent_a"],
        alarms=["overload_b"],
        estop=True,
        online=None,
        servo=[None, False],
        foreign_host={"address": 5, "frames": 12},
    )
    model.feed(state_topic(A, "left"), payload, False, T0)
    text = shown(model, T0)
    for said in ("✖ overcurrent_a", "▲ overload_b", "LATCHED", "address 5, 12 frames", "? off"):
        assert said in text, said


BAD = [
    (b"not json", "not JSON"),
    (b"[1, 2]", "not a JSON object"),
    (json.dumps({"v": 1, "time": T0}).encode(), "seq"),
    (unit_state(A, "left", time=float("nan")).replace(b"NaN", b'"x"'), "time"),
    (unit_state(A, "right"), "not its topic's"),  # unit in the payload is not the topic's
    (unit_state("plant-z", "left"), "fleet_id"),
    (unit_state(A, "left", estop="yes"), "estop"),
    (unit_state(A, "left", servo=[True]), "servo"),
    (unit_state(A, "left", errors="overcurrent"), "errors"),
    (unit_state(A, "left", measured={"a": "fast", "b": 0}), "measured"),
    (b"{" + b" " * 70_000 + b"}", "larger"),
    (b"\xff\xfe", "not JSON"),
]


@pytest.mark.parametrize(("payload", "said"), BAD)
def test_a_malformed_state_is_counted_and_said_never_a_crash(payload: bytes, said: str) -> None:
    model = fleet()
    model.feed(state_topic(A, "left"), payload, False, T0)
    robot = model.robots[A]
    assert (model.malformed, robot.malformed, robot.units) == (1, 1, {})
    assert said in model.problem
    assert "1 malformed" in shown(model, T0)
    model.feed(state_topic(A, "left"), unit_state(A, "left"), False, T0)  # then a good one
    assert "left" in robot.units


def test_malformed_status_events_and_health_are_counted_too() -> None:
    model = fleet()
    model.feed(status_topic(A), status(A, "sleeping"), True, T0)
    model.feed(
        status_topic(A),
        status(A).replace(b'"attach": null', b'"attach": 5'),
        True,
        T0,
    )
    model.feed(f"{PREFIX}/{A}/events", event(A, "x", "y").replace(b'"data": {}', b'"data": 1'), False, T0)  # fmt: skip
    model.feed(f"{PREFIX}/{A}/health", json.dumps({"v": 1, "time": T0, "seq": 1, "fleet_id": A}).encode(), False, T0)  # fmt: skip
    assert model.robots[A].malformed == 4 and model.robots[A].state is None


def test_another_version_is_counted_apart() -> None:
    model = fleet()
    model.feed(state_topic(A, "left"), unit_state(A, "left", v=2), False, T0)
    assert (model.wrong_version, model.malformed) == (1, 0)
    assert "version 2" in model.problem and "1 of another version" in shown(model, T0)


def test_commands_other_prefixes_and_unknown_topics_are_not_state() -> None:
    model = fleet()
    model.feed(
        f"{PREFIX}/all/cmd/estop",
        payloads.encode(payloads.estop_command(1, T0, sender="x", reason="r")),
        False,
        T0,
    )
    model.feed(f"{PREFIX}/{A}/cmd/estop", b"{}", False, T0)
    model.feed("abh3/v2/plant-a/status", status(A), True, T0)
    model.feed(f"{PREFIX}/{A}/something/new", b"{}", False, T0)
    assert model.robots == {} and model.unknown_topics == 1 and model.malformed == 0
    assert "No robot seen" in shown(model, T0)


def test_events_are_kept_and_bounded() -> None:
    model = fleet()
    for seq in range(1, EVENTS_KEPT + 10):
        model.feed(f"{PREFIX}/{A}/events", event(A, "error", f"e{seq}", seq=seq), False, T0)
    events = model.robots[A].events
    assert len(events) == EVENTS_KEPT and events[-1].text == f"e{EVENTS_KEPT + 9}"


def test_the_selected_robots_events_and_its_health_trouble_are_shown() -> None:
    model = fleet()
    online(model)
    topic = f"{PREFIX}/{A}/events"
    model.feed(topic, event(A, "estop", "latched by tui:operator", time=T0), False, T0)
    health = {
        "v": 1,
        "time": T0,
        "seq": 1,
        "fleet_id": A,
        "robot": "a",
        "buses": {
            "can0": {
                "frames_sent": 9,
                "frames_received": 9,
                "send_errors": 3,
                "state": "error_passive",
            }
        },
        "mqtt": {
            "queued": 0,
            "dropped": 12,
            "reconnects": 1,
            "not_heard": ["estop", "instant_actions"],
        },
    }
    model.feed(f"{PREFIX}/{A}/health", json.dumps(health).encode(), False, T0)
    text = shown(model, T0 + 1)
    assert "recent events of plant-a" in text and "latched by tui:operator" in text
    assert "bus can0: error_passive" in text and "12 messages dropped" in text
    assert "it does not hear the fleet's e-stops: the broker refused them" in text
    assert "VDA 5050 instantActions (a stopPause is an e-stop): the broker refused" in text
    assert "twists" not in text
    assert "recent events" not in shown(model, T0 + 1, selected=None)
    assert "bus can0" not in shown(model, T0 + 16)  # health is every 5 s: 15 s old is stale


# -- the commands ------------------------------------------------------------------------


def test_e_stop_payloads_carry_v_time_seq_sender_reason() -> None:
    model = fleet()
    online(model)
    online(model, B)
    commander = Commander("abh3-fleet-op-host-1", PREFIX)
    one = commander.build(model, A, clear=False, reason="smoke", now=T0 + 1)
    every = commander.build(model, None, clear=False, reason="smoke", now=T0 + 2)
    clear = commander.build(model, None, clear=True, reason="smoke", now=T0 + 3)
    assert (one.topic, every.topic, clear.topic) == (
        f"{PREFIX}/{A}/cmd/estop",
        f"{PREFIX}/all/cmd/estop",
        f"{PREFIX}/all/cmd/estop_clear",
    )
    assert json.loads(one.payload) == {
        "v": 1,
        "time": T0 + 1,
        "seq": 1,
        "sender": "abh3-fleet-op-host-1",
        "reason": "smoke",
    }
    assert [json.loads(s.payload)["seq"] for s in (one, every, clear)] == [1, 2, 3]
    assert every.robots == (A, B) and one.robots == (A,)


def test_what_is_said_of_a_command_is_what_was_seen() -> None:
    model = fleet()
    online(model)
    v5 = Commander("me", PREFIX)
    sent = v5.build(model, A, clear=False, reason="r", now=T0 + 1)
    assert "sending" in sent.summary()
    v5.acknowledged(sent, 0x87, "Not authorized")
    assert sent.summary() == f"e-stop {A} (seq 1): REFUSED by the broker: Not authorized (0x87)"

    quiet = Commander("me", PREFIX, v5=False)
    sent = quiet.build(model, A, clear=False, reason="r", now=T0 + 1)
    quiet.acknowledged(sent, 0, "Success")
    assert "sent, not confirmed" in sent.summary() and "no word yet" in sent.summary()
    # the state before the command does not count; the latch seen after it does
    quiet.observe(model)
    assert A not in sent.robot_said
    for unit in ("left", "right"):
        model.feed(state_topic(A, unit), unit_state(A, unit, estop=True), False, T0 + 1.2)
    quiet.observe(model)
    assert sent.summary() == f"e-stop {A} (seq 1): latched on {A}"

    nobody = v5.build(model, None, clear=False, reason="r", now=T0 + 2)
    v5.acknowledged(nobody, 0x10, "No matching subscribers")
    assert "no robot subscribes" in nobody.summary()


def refused(sent_topic: str, reason: str, sender: str | None, **more: object) -> bytes:
    """A refusal as the plugin says it: the topic, the reason, the MQTT 5 sender (null
    under 3.1.1), no seq."""
    data = {"topic": sent_topic, "reason": reason, "sender": sender, **more}
    return event(A, "fleet_command_refused", f"refused on {sent_topic}: {reason}", data=data)


def test_a_robots_refusal_event_is_said() -> None:
    model = fleet()
    online(model)
    commander = Commander("me", PREFIX)
    sent = commander.build(model, A, clear=True, reason="r", now=T0 + 1)
    commander.acknowledged(sent, 0, "Success")
    for not_ours in (
        refused(sent.topic, "stale", "else"),  # another sender's
        refused(f"{PREFIX}/all/cmd/estop_clear", "allow_estop_clear is false", "me"),
        event(A, "fleet_command_refused", "3 more", data={"refused_unsaid": 3}),
    ):
        model.feed(f"{PREFIX}/{A}/events", not_ours, False, T0 + 1.1)
        commander.observe(model)
        assert sent.robot_said == {}
    ours = refused(sent.topic, "allow_estop_clear is false", "me")
    model.feed(f"{PREFIX}/{A}/events", ours, False, T0 + 1.1)
    commander.observe(model)
    assert sent.summary().endswith(f"{A} refused: allow_estop_clear is false")


def test_a_refusal_outweighs_a_state_that_shows_what_was_asked() -> None:
    """A robot never latched shows "cleared" whether it obeyed a clear or refused it."""
    model = fleet()
    online(model)
    commander = Commander("me", PREFIX)
    sent = commander.build(model, A, clear=True, reason="r", now=T0 + 1)
    for unit in ("left", "right"):
        model.feed(state_topic(A, unit), unit_state(A, unit, estop=False), False, T0 + 1.1)
    commander.observe(model)
    assert sent.robot_said == {A: "cleared"}
    ours = refused(sent.topic, "allow_estop is false", "me")
    model.feed(f"{PREFIX}/{A}/events", ours, False, T0 + 1.2)
    commander.observe(model)
    assert sent.summary().endswith(f"{A} refused: allow_estop is false")


def test_under_3_1_1_a_refusal_on_the_commands_topic_is_taken_as_its() -> None:
    model = fleet()
    online(model)
    commander = Commander("me", PREFIX, v5=False)
    sent = commander.build(model, A, clear=False, reason="r", now=T0 + 1)
    model.feed(f"{PREFIX}/{A}/events", refused(sent.topic, "stale: 3.1 s old", None), False, T0)
    commander.observe(model)
    assert sent.robot_said == {}  # received before it was sent: not its
    model.feed(f"{PREFIX}/{A}/events", refused(sent.topic, "allow_estop is false", None), False, T0 + 1.1)  # fmt: skip
    commander.observe(model)
    assert sent.robot_said == {A: "allow_estop is false"}


def test_the_robots_obeyed_event_then_its_state_and_a_partial_fleet_are_said() -> None:
    model = fleet()
    online(model)
    online(model, B)
    commander = Commander("me", PREFIX)
    sent = commander.build(model, None, clear=False, reason="r", now=T0 + 1)
    commander.acknowledged(sent, 0, "Success")
    topic_a, topic_b = f"{PREFIX}/{A}/events", f"{PREFIX}/{B}/events"

    def obeyed(seq: int) -> bytes:
        return event(A, "fleet_command", "estop by me", data={"sender": "me", "seq": seq, "kind": "estop"})  # fmt: skip

    model.feed(topic_a, obeyed(7), False, T0 + 1.1)
    commander.observe(model)
    assert A not in sent.robot_said  # its seq is 7, not ours (1)
    model.feed(topic_a, obeyed(1), False, T0 + 1.1)
    commander.observe(model)
    assert sent.summary() == "e-stop all (seq 1): taken by the broker; obeyed by 1 of 2"
    reason = {"topic": sent.topic, "reason": "allow_estop is false", "sender": "me"}
    refusal = event(B, "fleet_command_refused", "refused", data=reason)
    model.feed(topic_b, refusal, False, T0 + 1.1)
    commander.observe(model)
    assert sent.summary().endswith(f"obeyed by 1 of 2; {B} refused: allow_estop is false")
    for unit in ("left", "right"):
        model.feed(state_topic(A, unit), unit_state(A, unit, estop=True), False, T0 + 1.2)
    commander.observe(model)
    assert f"latched on 1 of 2; {B} refused" in sent.summary()
    alone = commander.build(model, A, clear=False, reason="r", now=T0 + 2)
    model.feed(topic_a, obeyed(2), False, T0 + 2)
    commander.observe(model)
    assert alone.summary() == f"e-stop {A} (seq 2): obeyed by {A} (not yet seen latched)"


def test_the_network_threads_queue_is_bounded_in_messages_and_bytes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """paho's callback, called as paho would: a 10 MB message is held as its first 64 KiB
    (enough to say it is too large), and beyond the bounds the oldest are dropped, counted."""
    from types import SimpleNamespace

    from abh3_supervisor.clients.fleet import broker
    from abh3_supervisor.clients.fleet.broker import BrokerOptions, FleetClient

    client = FleetClient(BrokerOptions("127.0.0.1", 1883, tls=False), PREFIX, clock=lambda: T0)
    huge = SimpleNamespace(topic=state_topic(A, "left"), payload=b"x" * 10_000_000, retain=False)
    client._on_message(None, None, huge)
    (held,) = client.drain()
    assert len(held.payload) == reading.MAX_PAYLOAD + 1
    model = fleet()
    model.feed(*held)
    assert model.malformed == 1 and "larger than any payload" in model.problem
    monkeypatch.setattr(broker, "QUEUED", 3)
    for seq in range(1, 6):
        small = SimpleNamespace(topic=state_topic(A, "left"), payload=unit_state(A, "left", seq=seq), retain=False)  # fmt: skip
        client._on_message(None, None, small)
    assert client.dropped == 2
    assert [json.loads(m.payload)["seq"] for m in client.drain()] == [3, 4, 5]
    monkeypatch.setattr(broker, "QUEUED_BYTES", 3 * (reading.MAX_PAYLOAD + 1))
    for _ in range(5):
        client._on_message(None, None, huge)
    assert client.dropped == 4 and len(client.drain()) == 3


def test_the_default_client_id_is_a_safe_one_per_run(monkeypatch: pytest.MonkeyPatch) -> None:
    import getpass
    import os
    import socket

    from abh3_supervisor.clients.fleet import broker

    monkeypatch.setattr(getpass, "getuser", lambda: "op erator")
    monkeypatch.setattr(socket, "gethostname", lambda: "line3/#pc")
    monkeypatch.setattr(os, "getpid", lambda: 4242)
    assert broker.default_client_id() == "abh3-fleet-op_erator-line3__pc-4242"
