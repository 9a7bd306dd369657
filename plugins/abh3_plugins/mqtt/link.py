"""One robot's connections to the broker: its own client ids, its own last will.

Up to four paho clients per robot, each with one job:

* the main one (``abh3-{fleet_id}``): everything we publish — status, states, events,
  health — and its will, the retained ``status`` ``connection_broken``. It subscribes to
  nothing, so its acknowledgements never wait behind unread messages;
* the commands one (``abh3-{fleet_id}.cmd``): the fleet's twists, read at most
  ``INCOMING_PER_S`` a second. Beyond, paho's thread waits before reading the next: a
  flood queues in TCP and at the broker, and whatever came on that connection after it
  (the broker's acknowledgements too) comes as late — so nothing else is on it;
* the stop one (``abh3-{fleet_id}.stop``): the e-stop and clear topics only, never read
  behind a flood of other commands, and with no cap on messages: each is judged as it
  arrives, so a flood of junk there costs what judging it costs (a refusal is cheap) and
  never holds a valid e-stop behind it — its thread only rests when it used more than
  ``SHARE`` of a core (a flood faster than that is read at that pace);
* with ``vda5050`` on, the VDA 5050 one (``abh3-{fleet_id}.vda``: ``connection``, its
  will ``CONNECTIONBROKEN`` — one MQTT connection carries one last will — and
  ``instantActions``), not capped either: a ``startPause`` is an e-stop.

paho's own thread reads, writes, pings and reconnects each; a sender thread of ours moves
the outbox into the main client only while it is connected, with at most
``MAX_INFLIGHT`` messages paho has not written (or, at QoS 1 and 2, the broker not
acknowledged) yet: whatever the broker does, nothing but the bounded outbox grows, and
the hooks never wait for it.
"""

from __future__ import annotations

import functools
import itertools
import logging
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from paho.mqtt.subscribeoptions import SubscribeOptions

from abh3_plugins.mqtt.outbox import Message, Outbox
from abh3_plugins.mqtt.settings import Settings
from abh3_supervisor.plugin_api import fleet

payloads = fleet.payloads

log = logging.getLogger("abh3_plugins.mqtt")
MAX_INFLIGHT = 100  # messages handed to paho and not yet written or acknowledged
MAX_PACKET = 64 * 1024  # MQTT 5: the broker sends us nothing larger (commands are tiny)
# twists the commands connection takes per second (a burst of as many): beyond, paho's
# thread waits before reading the next, so a flood of twists is held back by TCP and the
# broker, not by our Python (which shares its interpreter lock with the bus loop). Only
# there: a wait on a connection that carries e-stops would hold every e-stop behind what
# came before it (a second of junk once held one 29 s, and it was refused as stale)
INCOMING_PER_S = 100.0
STOPS = ("estop", "estop_clear")  # on the stop connection, for this robot and for `all`
# the connections that only read: what they hear, as said and as health names it
LISTENERS = {"stop": ("e-stops", "estop"), "commands": ("twists", "twist")}
CAPPED = "commands"  # the one connection read at most INCOMING_PER_S (no e-stop on it)
# the others (e-stops, VDA 5050) read what comes as it comes, a flood too: their thread
# then runs flat out at real-time priority, and past the kernel's real-time share (95 %
# of a core) the bus loop would be throttled with it. So such a thread rests once it used
# more than SHARE of a core over WINDOW_S: a flood is read at half a core's pace, and a
# message after a quiet moment never waits
SHARE, WINDOW_S = 0.5, 0.01
# health's name for the VDA 5050 instantActions, where a stopPause comes from (an e-stop)
VDA_NOT_HEARD = "instant_actions"
RECONNECT_S = (1, 5)  # paho's back-off between attempts [s]: first, at most

OnMessage = Callable[["Link", mqtt.MQTTMessage], None]


def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("abh3-supervisor")
    except PackageNotFoundError:
        return "unknown"


class Link:
    """A robot's broker connection(s), started by :meth:`start`, ended by :meth:`close`."""

    def __init__(
        self,
        settings: Settings,
        fleet_id: str,
        robot: str,
        units: list[str],
        *,
        on_message: OnMessage,
        on_lost: Callable[[Link], None],
    ) -> None:
        self.settings, self.fleet_id, self.robot, self.units = settings, fleet_id, robot, units
        self.topics = fleet.Topics(fleet_id, settings.prefix, settings.manufacturer)
        self.outbox = Outbox(settings.queue, fleet_id)
        self.seq = payloads.Sequence()
        self.reconnects = 0
        self.connected = threading.Event()  # the birth said: the sender may publish
        self._ever = False
        # the birth waits for the main connection and for each listening one's topics
        # subscribed (or that connection refused), so that `online` never comes before an
        # e-stop or a twist would be heard
        self._birth = threading.Lock()
        self._main_up = False
        # the VDA 5050 connection's instantActions too (its stopPause is an e-stop)
        heard = [*LISTENERS, "vda"] if settings.vda5050 else list(LISTENERS)
        self._heard = dict.fromkeys(heard, False)
        self._said_refused: set[str] = set()  # listeners whose refusal was logged
        # the fleet's commands not heard: their connection or subscription refused (health)
        self.not_heard: set[str] = set()
        self._on_message, self._on_lost = on_message, on_lost
        self._closing = threading.Event()
        self._inflight: deque[mqtt.MQTTMessageInfo] = deque()
        self._tokens = (INCOMING_PER_S, time.monotonic())  # the capped one's: tokens, when
        self._windows: dict[int, tuple[float, float]] = {}  # per client: since, its CPU
        # taking a topic's seq and queueing its message are one step (any thread): each
        # topic's messages leave in the order of their seq
        self._numbering = threading.Lock()
        self._sender = threading.Thread(target=self._send, name=f"mqtt {fleet_id}", daemon=True)
        self.host, self.pid, self.version = socket.gethostname(), os.getpid(), version()
        self.client = self._client(fleet.client_id(fleet_id))
        self.client.on_pre_connect = self._pre_connect
        self.client.on_connect = self._connected
        self.client.on_disconnect = self._disconnected
        self.commands = self._listener("commands", fleet.commands_client_id(fleet_id))
        self.stop = self._listener("stop", fleet.stop_client_id(fleet_id))
        self.vda: mqtt.Client | None = None
        if settings.vda5050:
            self.vda = self._client(fleet.vda_client_id(fleet_id))
            self.vda.on_pre_connect = self._vda_pre_connect
            self.vda.on_connect = self._vda_connected
            self.vda.on_subscribe = self._vda_subscribed
            self.vda.on_disconnect = self._vda_disconnected
            self.vda.on_message = self._message

    # ------------------------------------------------------------ set-up

    def _client(self, cid: str) -> mqtt.Client:
        s = self.settings
        v5 = s.protocol == "5"
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=cid,
            protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
            clean_session=None if v5 else True,
        )
        if s.username is not None:
            client.username_pw_set(s.username, s.password())
        if s.tls is not None:
            client.tls_set(ca_certs=s.tls.ca, certfile=s.tls.cert, keyfile=s.tls.key)
        client.reconnect_delay_set(*RECONNECT_S)
        client.suppress_exceptions = True  # a raising callback would end paho's thread
        return client

    def start(self) -> None:
        """Connect in the background: nothing here waits for the broker."""
        properties = None
        if self.settings.protocol == "5":
            properties = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
            properties.MaximumPacketSize = MAX_PACKET
        for client in (self.client, self.commands, self.stop, self.vda):
            if client is not None:
                client.connect_async(
                    self.settings.host,
                    self.settings.port,
                    self.settings.keepalive_s,
                    properties=properties,
                )
                client.loop_start()
        self._sender.start()

    def status(self, state: str) -> dict[str, Any]:
        return payloads.status(
            self.seq(self.topics.status),
            time.time(),
            fleet_id=self.fleet_id,
            robot=self.robot,
            state=state,
            host=self.host,
            pid=self.pid,
            version=self.version,
            units=self.units,
            attach=self.settings.attach,
        )

    def connection(self, state: str) -> dict[str, Any]:
        return payloads.vda_connection(
            self.seq(self.topics.connection),
            time.time(),
            manufacturer=self.settings.manufacturer,
            fleet_id=self.fleet_id,
            state=state,
        )

    # ------------------------------------------------------------ paho's thread

    def _pre_connect(self, client: mqtt.Client, userdata: Any) -> None:
        # the will carries the time and seq of this attempt: the broker sends it later
        will = payloads.encode(self.status("connection_broken"))
        client.will_set(self.topics.status, will, self.settings.qos["status"], retain=True)

    def _vda_pre_connect(self, client: mqtt.Client, userdata: Any) -> None:
        will = payloads.encode(self.connection("connection_broken"))
        client.will_set(self.topics.connection, will, 1, retain=True)

    def _connected(
        self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, props: Any
    ) -> None:
        if reason.is_failure:
            log.warning(
                "mqtt %s: %s refused the connection: %s", self.fleet_id, self.settings.url, reason
            )
            return
        with self._birth:
            self._main_up = True
            self._born_if_ready()

    def _born_if_ready(self) -> None:
        """The birth, once the main connection is up and the e-stops and twists are heard
        (the lock held; any of paho's threads)."""
        if not (self._main_up and all(self._heard.values())) or self.connected.is_set():
            return
        # the birth first: the retained status says online before anything else
        with self._numbering:
            self.client.publish(
                self.topics.status,
                payloads.encode(self.status("online")),
                self.settings.qos["status"],
                retain=True,
            )
        if self._ever:
            self.reconnects += 1
            log.info("mqtt %s: connected again to %s", self.fleet_id, self.settings.url)
        else:
            log.info("mqtt %s: connected to %s", self.fleet_id, self.settings.url)
        self._ever = True
        self.connected.set()

    # ------------------------------------------------------------ the listening ones

    def _listener(self, name: str, cid: str) -> mqtt.Client:
        """A connection that only reads: ``name``'s topics (:data:`LISTENERS`)."""
        client = self._client(cid)
        client.on_connect = functools.partial(self._listener_connected, name)
        client.on_subscribe = functools.partial(self._listener_subscribed, name)
        client.on_disconnect = functools.partial(self._listener_disconnected, name)
        client.on_message = self._capped if name == CAPPED else self._message
        return client

    def _listener_topics(self, name: str) -> list[str]:
        t = self.topics
        if name == "stop":  # the robot's and everyone's
            return [t.command(kind, everyone=every) for kind in STOPS for every in (False, True)]
        return [t.command("twist")]

    def _listener_connected(
        self, name: str, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, props: Any
    ) -> None:
        if reason.is_failure:  # not heard; the birth is not held for it
            # said once (the main connection says a refusal of its own, alike)
            if self._main_up and name not in self._said_refused:
                self._said_refused.add(name)
                log.warning(
                    "mqtt %s: the %s connection was refused: %s (%s from the fleet are not heard)",
                    self.fleet_id,
                    name,
                    reason,
                    LISTENERS[name][0],
                )
            self.not_heard.add(LISTENERS[name][1])
            self._heard_now(name)
            return
        self._said_refused.discard(name)
        client.subscribe([(topic, self._options()) for topic in self._listener_topics(name)])

    def _listener_subscribed(
        self, name: str, client: mqtt.Client, userdata: Any, mid: int, codes: Any, props: Any
    ) -> None:
        what, kind = LISTENERS[name]
        refused = _refused(self._listener_topics(name), codes)
        if not refused:
            self.not_heard.discard(kind)
        else:  # a broker that refuses at SUBACK (the ACL): the birth is not held; any
            # topic refused counts as not heard (the robot's own or everyone's e-stop)
            self.not_heard.add(kind)
            log.warning(
                "mqtt %s: the broker refused the subscription to %s: %s",
                self.fleet_id,
                what,
                ", ".join(refused),
            )
        self._heard_now(name)

    def _heard_now(self, name: str) -> None:
        with self._birth:
            self._heard[name] = True
            self._born_if_ready()

    def _unheard(self, name: str) -> bool:
        """``name``'s connection lost: the next birth waits for it; whether the main
        connection is still up (else that one says the broker is lost)."""
        with self._birth:
            self._heard[name] = False
            return self._main_up

    def _listener_disconnected(
        self, name: str, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, props: Any
    ) -> None:
        alone = self._unheard(name)
        if alone and not self._closing.is_set():
            what = f"the {name} connection was lost ({reason}); reconnecting"
            log.warning("mqtt %s: %s", self.fleet_id, what)

    def _vda_connected(
        self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, props: Any
    ) -> None:
        if reason.is_failure:  # said by the main connection, refused alike
            self.not_heard.add(VDA_NOT_HEARD)
            self._heard_now("vda")  # the birth is not held for it
            return
        # subscribed first: the broker takes one connection's packets in order, so whoever
        # reads ONLINE can be sure its instantActions are heard
        client.subscribe([(self.topics.instant_actions, self._options())])
        online = payloads.encode(self.connection("online"))
        client.publish(self.topics.connection, online, 1, retain=True)

    def _vda_subscribed(
        self, client: mqtt.Client, userdata: Any, mid: int, codes: Any, props: Any
    ) -> None:
        refused = _refused([self.topics.instant_actions], codes)
        if not refused:
            self.not_heard.discard(VDA_NOT_HEARD)
        else:  # its stopPause is an e-stop the fleet cannot give: health says so
            self.not_heard.add(VDA_NOT_HEARD)
            log.warning(
                "mqtt %s: the broker refused the subscription to %s",
                self.fleet_id,
                ", ".join(refused),
            )
        self._heard_now("vda")  # whoever reads our status online is heard there too

    def _vda_disconnected(
        self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, props: Any
    ) -> None:
        self._unheard("vda")  # the main connection says a loss of the broker

    def _options(self) -> Any:
        """A command subscription's QoS; under MQTT 5 with "retain as published", so that a
        command published retained keeps its flag even live and is refused as well (3.1.1
        flags only the broker's replays)."""
        qos = self.settings.qos["commands"]
        if self.settings.protocol != "5":
            return qos
        return SubscribeOptions(qos=qos, retainAsPublished=True)

    def _disconnected(
        self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, props: Any
    ) -> None:
        with self._birth:
            self._main_up = False
            was = self.connected.is_set()
            self.connected.clear()
        if was and not self._closing.is_set():
            log.warning(
                "mqtt %s: lost the broker %s (%s); reconnecting",
                self.fleet_id,
                self.settings.url,
                reason,
            )
            self._on_lost(self)

    def _message(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        """paho's thread of an uncapped connection: judged as soon as it is read, whatever
        came before it (e-stops are read here); a rest, if any, only after it."""
        self._judge(message)
        self._share(id(client))

    def _capped(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        """paho's thread of the commands connection: a twist, after its token (the cap is
        all it is held to)."""
        self._take_token()
        self._judge(message)

    def _judge(self, message: mqtt.MQTTMessage) -> None:
        try:
            self._on_message(self, message)
        except Exception:  # a bug of ours must not end paho's thread (and its reconnects)
            log.exception(
                "mqtt %s: a message on %s could not be handled", self.fleet_id, message.topic
            )

    def _share(self, key: int) -> None:
        """Rest (in paho's thread, between two messages) when it used more than SHARE of
        a core over the last window: only under a flood, and for no longer than brings it
        back to SHARE."""
        now, cpu = time.monotonic(), time.thread_time()
        since, used = self._windows.get(key, (now, cpu))
        if now - since < WINDOW_S:
            self._windows.setdefault(key, (since, used))
            return
        busy = cpu - used
        if busy > SHARE * (now - since):  # a window's rest at most: a long read (a 10 MB
            # message under 3.1.1) costs the next message 10 ms, a flood half the time
            self._closing.wait(min(WINDOW_S, busy / SHARE - (now - since)))
        self._windows[key] = (time.monotonic(), time.thread_time())

    def _take_token(self) -> None:
        """Wait (in the commands connection's thread, the only one that takes tokens) until
        it may handle another message."""
        now = time.monotonic()
        tokens, then = self._tokens
        tokens = min(INCOMING_PER_S, tokens + (now - then) * INCOMING_PER_S)
        if tokens < 1.0:
            self._closing.wait((1.0 - tokens) / INCOMING_PER_S)
            tokens, now = 1.0, time.monotonic()
        self._tokens = (tokens - 1.0, now)

    # ------------------------------------------------------------ our sender thread

    def put(
        self,
        topic: str,
        build: Callable[[int, float], dict[str, Any]],
        qos: int,
        *,
        retain: bool,
        lossy: bool,
    ) -> None:
        """Queue ``build(seq, time)`` for the broker; returns at once (any thread). The seq
        is taken and the message queued under one lock: taken apart, three threads (the
        hooks', the state timer, paho's refusals) once queued an event's 238 before its
        237. Building a payload is all the lock is held for besides the deque."""
        with self._numbering:
            payload = payloads.encode(build(self.seq(topic), time.time()))
            self.outbox.put(Message(topic, payload, qos, retain), lossy=lossy)

    def _send(self) -> None:
        while not (self._closing.is_set() and not len(self.outbox)):
            if not self.connected.wait(0.2):
                self._inflight.clear()  # paho drops or resends these itself
                if self._closing.is_set():
                    return
                continue
            while self._inflight and self._inflight[0].is_published():
                self._inflight.popleft()
            if len(self._inflight) >= MAX_INFLIGHT:
                self._closing.wait(0.02)  # the broker is slow: the outbox holds the rest
                continue
            message = self.outbox.take(0.2)
            if message is None:
                continue
            info = self.client.publish(message.topic, message.payload, message.qos, message.retain)
            if info.rc is MQTTErrorCode.MQTT_ERR_SUCCESS:
                self._inflight.append(info)
            else:
                self.outbox.dropped += 1  # lost between our check and paho's: counted

    def drained(self) -> bool:
        """Everything queued was written (or there is no broker to write it to)."""
        if not self.connected.is_set():
            return True
        return not len(self.outbox) and all(i.is_published() for i in list(self._inflight))

    # ------------------------------------------------------------ the way out

    def say_offline(self) -> None:
        """The orderly death: ``offline`` after everything queued, the last states too."""
        with self._numbering:
            status = payloads.encode(self.status("offline"))
            qos = self.settings.qos["status"]
            self.outbox.put_last(Message(self.topics.status, status, qos, True))

    def close(self) -> None:
        """Disconnect in order (no last will), once the sender is done or given up; paho's
        threads are told to end, and :meth:`join` waits for them."""
        self._closing.set()
        self.outbox.close()
        self._sender.join(0.5)
        if self.vda is not None and self.vda.is_connected():
            info = self.vda.publish(
                self.topics.connection, payloads.encode(self.connection("offline")), 1, retain=True
            )
            info.wait_for_publish(0.3)
        for client in self._clients():
            client.disconnect()

    def join(self) -> None:
        """paho's threads ended. One waiting to reconnect takes up to a second to notice
        it was told (:meth:`close`): told all first, every link's, the waits overlap
        rather than add up past ``abh3_stop``'s deadline."""
        for client in self._clients():
            client.loop_stop()

    def _clients(self) -> list[mqtt.Client]:
        return [c for c in (self.vda, self.commands, self.stop, self.client) if c is not None]


def _refused(topics: list[str], codes: Any) -> list[str]:
    """The topics a SUBACK refused, each with its reason: its codes answer the topics in
    the order they were asked, and a topic a broker's short answer leaves out is not heard
    either."""
    return [
        f"{topic} ({'no answer' if code is None else code})"
        for topic, code in itertools.zip_longest(topics, codes)
        if code is None or code.is_failure
    ]
