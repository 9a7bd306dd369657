"""A robot's connections (plugins/abh3_plugins/mqtt/link.py) without a broker: paho's
callbacks called as paho calls them, on a link never started."""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import MQTTErrorCode
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

from abh3_plugins.mqtt.link import LISTENERS, WINDOW_S, Link
from abh3_plugins.mqtt.plugin import MqttPlugin
from abh3_plugins.mqtt.settings import Settings

OK = ReasonCode(PacketTypes.CONNACK, "Success")
NOT_AUTHORIZED = ReasonCode(PacketTypes.CONNACK, "Not authorized")
GRANTED = ReasonCode(PacketTypes.SUBACK, "Granted QoS 1")
REFUSED = ReasonCode(PacketTypes.SUBACK, "Not authorized")
THREADS, PER_THREAD = 8, 400  # publishing the same topics at once


def new_link(*, vda5050: bool) -> Link:
    return Link(
        Settings(name="t", vda5050=vda5050),
        "t-rover",
        "rover",
        ["front"],
        on_message=lambda link, message: None,
        on_lost=lambda link: None,
    )


@pytest.fixture
def link() -> Link:
    return new_link(vda5050=False)


def client(link: Link, name: str) -> Any:
    return link.commands if name == "commands" else link.stop


def connect(link: Link, name: str, reason: ReasonCode = OK) -> None:
    """paho's ``on_connect`` of the listening connection ``name`` (as the link set it)."""
    client(link, name).on_connect(client(link, name), None, None, reason, None)


def subscribed(link: Link, name: str, *codes: ReasonCode) -> None:
    """paho's ``on_subscribe``: ``codes``, or every topic of ``name`` granted."""
    answer = list(codes) or [GRANTED] * len(link._listener_topics(name))
    client(link, name).on_subscribe(client(link, name), None, 1, answer, None)


def test_online_waits_for_the_e_stops_and_the_twists_to_be_heard(link: Link) -> None:
    """Whoever reads ``online`` is heard: the twists' own connection is waited for as the
    e-stops' is (it was, while the twists were read on the main connection)."""
    link._connected(link.client, None, None, OK, None)
    for name in LISTENERS:
        assert not link.connected.is_set()
        connect(link, name)
        assert not link.connected.is_set()  # connected, not yet subscribed
        subscribed(link, name)
    assert link.connected.is_set()


def test_a_refused_subscription_is_said_and_holds_nothing_back(
    link: Link, caplog: pytest.LogCaptureFixture
) -> None:
    """A broker whose ACL refuses at SUBACK: the warning names what is not heard; the
    robot still says ``online`` (as for a refused connection)."""
    link._connected(link.client, None, None, OK, None)
    subscribed(link, "commands")
    with caplog.at_level(logging.WARNING, logger="abh3_plugins.mqtt"):
        subscribed(link, "stop", REFUSED, GRANTED, GRANTED, GRANTED)
    assert link.connected.is_set()
    said = [r.getMessage() for r in caplog.records]
    assert said == [
        "mqtt t-rover: the broker refused the subscription to e-stops: "
        "abh3/v1/t-rover/cmd/estop (Not authorized)"
    ]
    assert link.not_heard == {"estop"}  # the robot's health tells the fleet so
    subscribed(link, "stop", GRANTED)  # an answer short of the four topics asked
    assert link.not_heard == {"estop"}
    subscribed(link, "stop")  # granted on the next connection
    assert link.not_heard == set()


def test_a_refused_listening_connection_is_said_once_not_at_every_retry(
    link: Link, caplog: pytest.LogCaptureFixture
) -> None:
    link._connected(link.client, None, None, OK, None)
    subscribed(link, "stop")
    with caplog.at_level(logging.WARNING, logger="abh3_plugins.mqtt"):
        for _ in range(3):  # paho tries again every 1-5 s
            connect(link, "commands", NOT_AUTHORIZED)
    assert link.connected.is_set()  # not held for twists that cannot come
    assert link.not_heard == {"twist"}
    said = [r.getMessage() for r in caplog.records]
    assert said == [
        "mqtt t-rover: the commands connection was refused: Not authorized "
        "(twists from the fleet are not heard)"
    ]
    connect(link, "commands")  # accepted at last; a later refusal is said again
    with caplog.at_level(logging.WARNING, logger="abh3_plugins.mqtt"):
        connect(link, "commands", NOT_AUTHORIZED)
    assert len(caplog.records) == 2


def test_a_listening_connection_lost_alone_is_said(
    link: Link, caplog: pytest.LogCaptureFixture
) -> None:
    """The main connection says a loss of the broker; one lost on its own (paho before 2.2
    closed the twists' connection by its own keep-alive under a flood) is said too."""
    link._connected(link.client, None, None, OK, None)
    lost = ReasonCode(PacketTypes.DISCONNECT, "Keep alive timeout")
    with caplog.at_level(logging.WARNING, logger="abh3_plugins.mqtt"):
        client(link, "commands").on_disconnect(link.commands, None, None, lost, None)
    assert [r.getMessage() for r in caplog.records] == [
        "mqtt t-rover: the commands connection was lost (Keep alive timeout); reconnecting"
    ]


def test_online_waits_for_vda5050_instant_actions_too() -> None:
    """A VDA 5050 ``stopPause`` is an e-stop: with ``vda5050`` on, the status says
    ``online`` only once instantActions are subscribed (a fleet that read ``online`` and
    sent at once found the subscription not yet made: CI on 78fb17f)."""
    link = new_link(vda5050=True)
    link._connected(link.client, None, None, OK, None)
    for name in LISTENERS:
        subscribed(link, name)
    assert not link.connected.is_set() and link.vda is not None
    link._vda_subscribed(link.vda, None, 1, [GRANTED], None)
    assert link.connected.is_set()


def test_refused_vda5050_instant_actions_are_told_in_health(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A broker that refuses instantActions (their connection, or at SUBACK) leaves the
    fleet without the stopPause, an e-stop: health's ``not_heard`` says so, as for the
    robot's own e-stop topic, until a later connection is granted them."""
    link = new_link(vda5050=True)
    assert link.vda is not None
    link._connected(link.client, None, None, OK, None)
    for name in LISTENERS:
        subscribed(link, name)
    with caplog.at_level(logging.WARNING, logger="abh3_plugins.mqtt"):
        link._vda_subscribed(link.vda, None, 1, [REFUSED], None)
    assert link.connected.is_set()  # not held back for what cannot come
    assert link.not_heard == {"instant_actions"}
    assert [r.getMessage() for r in caplog.records] == [
        "mqtt t-rover: the broker refused the subscription to "
        "uagv/v2/waco-giken-abh3/t-rover/instantActions (Not authorized)"
    ]
    link._vda_subscribed(link.vda, None, 1, [GRANTED], None)  # granted on reconnecting
    assert link.not_heard == set()
    link._vda_connected(link.vda, None, None, NOT_AUTHORIZED, None)
    assert link.not_heard == {"instant_actions"}


class Written:
    """What paho's ``publish`` returns: written and acknowledged at once."""

    rc = MQTTErrorCode.MQTT_ERR_SUCCESS

    def is_published(self) -> bool:
        return True


def test_each_topic_leaves_in_the_order_of_its_seq(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fleet events once left out of order (``events`` seq 237 after 238): the seq was
    taken and the message queued without one lock across both, by the hooks' thread, the
    state timer and paho's (refusals). Many threads here publish events and states through
    the plugin's own path, thread switches forced often; the order handed to paho must be
    each topic's seq, none missing."""
    link = new_link(vda5050=False)
    link.outbox.size = 1_000_000  # nothing dropped: every seq must be handed on
    plugin = MqttPlugin()
    handed: list[tuple[str, int]] = []

    def publish(topic: str, payload: bytes, qos: int, retain: bool) -> Written:
        handed.append((topic, json.loads(payload)["seq"]))
        return Written()

    monkeypatch.setattr(link.client, "publish", publish)
    link.connected.set()
    link._sender.start()  # the link's own sender, as started: it hands paho the outbox

    def publisher(n: int) -> None:
        for i in range(PER_THREAD):
            plugin.event(link, None, "notice", f"{n}.{i}")
            link.put(
                link.topics.state("front"),
                lambda seq, now: {"seq": seq, "time": now},
                0,
                retain=True,
                lossy=True,
            )

    threads = [threading.Thread(target=publisher, args=(n,)) for n in range(THREADS)]
    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # a thread switch almost anywhere: the race's window
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(switch)
    deadline = time.monotonic() + 30
    while len(handed) < 2 * THREADS * PER_THREAD and time.monotonic() < deadline:
        time.sleep(0.01)  # the sender drains the outbox on its own thread
    link.close()
    for topic in (link.topics.events, link.topics.state("front")):
        seqs = [seq for t, seq in handed if t == topic]
        assert seqs == list(range(1, THREADS * PER_THREAD + 1)), topic


def test_the_e_stop_connections_are_not_capped_and_judge_before_any_rest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Refused messages once used the e-stop connection's budget of 100 a second, and a
    real e-stop waited behind a second of junk until it was stale. Only the twists are
    capped now; the e-stop and VDA 5050 connections judge each message as it is read,
    and rest (between messages, a window at most) only when they used over half a core."""
    judged: list[bytes | bytearray] = []
    link = Link(
        Settings(name="t", vda5050=True),
        "t-rover",
        "rover",
        ["front"],
        on_message=lambda link, message: judged.append(message.payload),
        on_lost=lambda link: None,
    )
    assert link.vda is not None
    rests: list[tuple[int, float]] = []  # (messages judged by then, how long)
    monkeypatch.setattr(link._closing, "wait", lambda s: rests.append((len(judged), s)))

    def deliver(client: Any, n: int) -> None:
        for i in range(n):
            message = mqtt.MQTTMessage(topic=b"x")
            message.payload = b"%d" % i
            client.on_message(client, None, message)

    deliver(link.commands, 150)  # twists: past the burst of 100 each waits for a token
    assert len(judged) == 150 and 100 <= rests[0][0] < 150
    rests.clear()
    start = time.monotonic()
    for listener in (link.stop, link.vda):
        deliver(listener, 5000)  # a flood of junk, read flat out: no token taken
    elapsed = time.monotonic() - start
    assert len(judged) == 150 + 2 * 5000
    # the CPU share's rests: one a window at most (a cap would have made ~10,000)
    assert len(rests) <= 2 * (elapsed / WINDOW_S + 1)
    assert all(s <= WINDOW_S for _, s in rests)
