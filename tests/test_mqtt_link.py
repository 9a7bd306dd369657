"""A robot's connections (plugins/abh3_plugins/mqtt/link.py) without a broker: paho's
callbacks called as paho calls them, on a link never started."""

from __future__ import annotations

import logging
from typing import Any

import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.reasoncodes import ReasonCode

from abh3_plugins.mqtt.link import LISTENERS, Link
from abh3_plugins.mqtt.settings import Settings

OK = ReasonCode(PacketTypes.CONNACK, "Success")
NOT_AUTHORIZED = ReasonCode(PacketTypes.CONNACK, "Not authorized")
GRANTED = ReasonCode(PacketTypes.SUBACK, "Granted QoS 1")
REFUSED = ReasonCode(PacketTypes.SUBACK, "Not authorized")


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
