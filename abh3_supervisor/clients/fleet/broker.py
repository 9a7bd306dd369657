"""The MQTT side of ``abh3 fleet``: its options, and a paho-mqtt client that subscribes to
the prefix, queues what arrives for the UI thread and publishes commands (QoS 1).

paho-mqtt is optional (the ``mqtt`` extra): imported only here, only when connecting.
The password never leaves this module's option object: not printed, not in a repr, never
taken from the command line itself (an environment variable's name or a file).
"""

from __future__ import annotations

import getpass
import os
import socket
import ssl
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple
from urllib.parse import urlsplit

from abh3_supervisor.clients.fleet.reading import MAX_PAYLOAD
from abh3_supervisor.errors import Abh3Error, RunError, install_hint
from abh3_supervisor.fleet import safe

if TYPE_CHECKING:
    import paho.mqtt.client as paho

PORTS = {"mqtt": 1883, "mqtts": 8883}
KEEPALIVE_S = 10
CONNECT_TIMEOUT_S = 10.0  # the TCP/TLS connect and the broker's CONNACK
QUEUED = 20_000  # messages waiting for the UI thread; beyond, the oldest are dropped, counted
QUEUED_BYTES = 32 * 1024 * 1024  # and their bytes: a flood of big ones cannot grow memory
INSTALL = f"paho-mqtt is not installed: {install_hint('mqtt')}"


class Received(NamedTuple):
    topic: str
    payload: bytes
    retained: bool
    time: float  # our clock, when the network thread got it


@dataclass(frozen=True)
class BrokerOptions:
    host: str
    port: int
    tls: bool
    protocol: str = "5"  # or "3.1.1"
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    client_id: str = ""
    keepalive_s: int = KEEPALIVE_S

    @property
    def v5(self) -> bool:
        return self.protocol == "5"

    def where(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"


def parse_url(text: str) -> tuple[bool, str, int]:
    """``mqtt://host[:port]`` or ``mqtts://host[:port]``: (tls, host, port). A bad URL is a
    usage error (exit 2)."""
    try:
        url = urlsplit(text)
        port = url.port
    except ValueError as exc:
        raise Abh3Error(f"--broker {text!r}: {exc}") from None
    if url.scheme not in PORTS:
        raise Abh3Error(f"--broker {text!r}: not mqtt://host:1883 or mqtts://host:8883")
    if not url.hostname or url.path not in ("", "/") or url.query or url.username:
        raise Abh3Error(
            f"--broker {text!r}: a host and an optional port only (credentials: "
            "--username and --password-env/--password-file)"
        )
    return url.scheme == "mqtts", url.hostname, port or PORTS[url.scheme]


def read_password(env: str | None, file: Path | None) -> str | None:
    """The password from the environment variable named ``env`` or from ``file`` (its first
    line); the value itself is never on the command line, nor said in an error."""
    if env is not None:
        value = os.environ.get(env)
        if value is None:
            raise Abh3Error(f"--password-env {env}: the environment has no {env}")
        return value
    if file is not None:
        try:
            lines = file.read_text().splitlines()
        except OSError as exc:
            raise Abh3Error(f"--password-file {file}: {exc.strerror}") from None
        return lines[0] if lines else ""
    return None


def default_client_id() -> str:
    """``abh3-fleet-{user}-{host}-{pid}``: the ``sender`` of its commands, one per run —
    a robot obeys a sender's ``seq`` only above the last it obeyed, and each run counts
    from 1 (docs/fleet.md, "The fleet view")."""
    raw = f"abh3-fleet-{getpass.getuser()}-{socket.gethostname()}-{os.getpid()}"
    return safe(raw)


def check_files(options: BrokerOptions) -> None:
    for name, path in (("--ca", options.ca), ("--cert", options.cert), ("--key", options.key)):
        if path is not None and not path.is_file():
            raise Abh3Error(f"{name} {path}: no such file")
    if options.key is not None and options.cert is None:
        raise Abh3Error("--key needs --cert (the client certificate it belongs to)")


class FleetClient:
    """One connection to the broker, its network on paho's own thread."""

    def __init__(
        self, options: BrokerOptions, prefix: str, clock: Callable[[], float] = time.time
    ) -> None:
        self.options, self.prefix, self.clock = options, prefix.rstrip("/"), clock
        self.received: deque[Received] = deque()  # bounded in _on_message
        self.acks: deque[tuple[int, int, str]] = deque()  # mid, reason code, its name
        self.dropped = 0
        self._bytes = 0
        self._lock = threading.Lock()
        self.connected = False
        self.changed = clock()  # when it connected or was lost
        self.lost_why = ""
        self.reconnects = 0
        self._first = threading.Event()
        self._refused: str | None = None
        self._client: paho.Client | None = None

    def connect(self, timeout: float = CONNECT_TIMEOUT_S) -> None:
        """Connect and subscribe, or raise RunError saying why (exit 1): unreachable, TLS,
        credentials refused, no answer."""
        try:
            import paho.mqtt.client as mqtt
            from paho.mqtt.enums import CallbackAPIVersion
        except ImportError:
            raise RunError(INSTALL) from None
        o = self.options
        protocol = mqtt.MQTTv5 if o.v5 else mqtt.MQTTv311
        client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=o.client_id, protocol=protocol)
        client.connect_timeout = timeout
        client.reconnect_delay_set(1, 10)
        if o.username is not None:
            client.username_pw_set(o.username, o.password)
        if o.tls:
            try:
                client.tls_set(
                    ca_certs=str(o.ca) if o.ca else None,
                    certfile=str(o.cert) if o.cert else None,
                    keyfile=str(o.key) if o.key else None,
                )
            except (OSError, ValueError) as exc:  # ssl.SSLError is an OSError
                raise RunError(f"TLS set-up: {exc}") from None
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.on_publish = self._on_publish
        self._client = client
        try:
            client.connect(o.host, o.port, keepalive=o.keepalive_s)
        except ssl.SSLCertVerificationError as exc:
            raise RunError(
                f"TLS failure with {o.where()}: certificate verify failed: {exc.verify_message}"
                " (--ca: the CA that signed the broker's certificate)"
            ) from None
        except ssl.SSLError as exc:
            raise RunError(f"TLS failure with {o.where()}: {exc.reason or exc}") from None
        except socket.gaierror as exc:
            raise RunError(f"broker {o.where()}: cannot resolve {o.host}: {exc.strerror}") from None
        except (OSError, TimeoutError) as exc:
            why = exc.strerror or str(exc) or type(exc).__name__
            if o.tls and not isinstance(exc, ConnectionRefusedError | TimeoutError):
                # reached, then dropped in the handshake: a plain listener, or TLS refused
                raise RunError(
                    f"TLS failure with {o.where()}: {why} during the handshake (is it a TLS "
                    "listener? does it want a client certificate?)"
                ) from None
            raise RunError(f"broker {o.where()} unreachable: {why}") from None
        client.loop_start()
        if not self._first.wait(timeout):
            self.close()
            raise RunError(f"broker {o.where()}: no answer to the connection in {timeout:.0f} s")
        if self._refused is not None:
            self.close()
            raise RunError(self._refused)

    def close(self) -> None:
        if self._client is not None:
            self._client.disconnect()
            self._client.loop_stop()
            self._client = None

    def publish(self, topic: str, payload: bytes) -> tuple[int, str | None]:
        """Send with QoS 1 (never retained: a robot never obeys a retained command);
        (mid, why it is not sent now) — paho keeps it for the reconnect."""
        assert self._client is not None, "publish before connect"
        props = None
        if self.options.v5:
            from paho.mqtt.packettypes import PacketTypes
            from paho.mqtt.properties import Properties

            props = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
            props.UserProperty = ("sender", self.options.client_id)
        info = self._client.publish(topic, payload, qos=1, retain=False, properties=props)
        if info.rc != 0:
            return info.mid, "not connected to the broker: queued until it is back"
        return info.mid, None

    def drain(self) -> list[Received]:
        with self._lock:
            out, self._bytes = list(self.received), 0
            self.received.clear()
        return out

    def take_acks(self) -> list[tuple[int, int, str]]:
        out: list[tuple[int, int, str]] = []
        while self.acks:
            out.append(self.acks.popleft())
        return out

    def describe(self, now: float) -> str:
        o = self.options
        since = now - self.changed
        if self.connected:
            return (
                f"broker: connected to {o.where()} (MQTT {o.protocol}) as {o.client_id}"
                + (f", {self.reconnects} reconnects" if self.reconnects else "")
                + (f"; {self.dropped} messages dropped (too many at once)" if self.dropped else "")
            )
        return (
            f"broker: LOST {since:.0f} s ago ({self.lost_why}); reconnecting — what is "
            "shown is as of then"
        )

    # -- paho's thread ----------------------------------------------------------------

    def _on_connect(self, client: Any, userdata: Any, flags: Any, rc: Any, props: Any) -> None:
        if rc.is_failure:
            if self._first.is_set():
                self.lost_why = f"the broker refused the reconnection: {rc}"
            else:
                self._refused = f"broker {self.options.where()} refused the connection: {rc}"
                self._first.set()
            return
        if self._first.is_set():
            self.reconnects += 1
        self.connected, self.changed = True, self.clock()
        client.subscribe(f"{self.prefix}/#", qos=1)  # again after a reconnect: retained replays
        self._first.set()

    def _on_disconnect(self, client: Any, userdata: Any, flags: Any, rc: Any, props: Any) -> None:
        if not self._first.is_set():  # closed before the broker answered: say it now
            o = self.options
            self._refused = (
                f"TLS failure with {o.where()}: the broker closed the connection after the "
                "handshake — does it want a client certificate (--cert, --key)?"
                if o.tls  # TLS 1.3: the broker checks the client's certificate after it
                else f"broker {o.where()} closed the connection before answering"
            )
            self._first.set()
        if self.connected:
            self.changed = self.clock()
        self.connected, self.lost_why = False, str(rc)

    def _on_message(self, client: Any, userdata: Any, message: Any) -> None:
        # one bigger than any payload of the contract is only counted (as too large): its
        # start is enough to say so, and all of it is never held
        payload = bytes(message.payload[: MAX_PAYLOAD + 1])
        with self._lock:
            while self.received and (
                len(self.received) >= QUEUED or self._bytes + len(payload) > QUEUED_BYTES
            ):
                self._bytes -= len(self.received.popleft().payload)
                self.dropped += 1
            self.received.append(
                Received(message.topic, payload, bool(message.retain), self.clock())
            )
            self._bytes += len(payload)

    def _on_publish(self, client: Any, userdata: Any, mid: int, rc: Any, props: Any) -> None:
        self.acks.append((mid, int(rc.value), str(rc)))
