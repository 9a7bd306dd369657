"""A real MQTT client for the tests (paho), as a fleet or an observer would be, that
validates every payload it receives against the contract's JSON Schemas (and the VDA 5050
ones) and can wait for a message; and a headless supervisor with the ``mqtt`` plugin in
a process of its own."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jsonschema
import paho.mqtt.client as mqtt
import yaml
from paho.mqtt.enums import CallbackAPIVersion, MQTTProtocolVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from abh3_supervisor.fleet import schemas
from abh3_supervisor.fleet.topics import PREFIX, VDA_PREFIX
from tests.support.mosquitto import Broker, password

ROOT = Path(__file__).resolve().parent.parent.parent
VDA = ROOT / "tests" / "data" / "vda5050"
RUN = [sys.executable, "-m", "abh3_supervisor", "run"]
SUFFIX = {"status": "status", "state": "unit_state", "events": "event", "health": "health"}
CMD = {"estop": "estop_command", "estop_clear": "estop_command", "twist": "twist_command"}


def vda_schema(name: str) -> dict[str, Any]:
    schema: dict[str, Any] = json.loads((VDA / f"{name}.schema").read_text("utf-8"))
    return schema


def _validator(schema: dict[str, Any]) -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(
        schema, format_checker=jsonschema.Draft202012Validator.FORMAT_CHECKER
    )


VALIDATORS = {name: _validator(schemas.load(name)) for name in schemas.NAMES}
VDA_VALIDATORS = {n: _validator(vda_schema(n)) for n in ("connection", "instantActions")}


def schema_of(topic: str) -> jsonschema.Draft202012Validator | None:
    """The validator of a topic's payload, or None for a topic of no schema of ours."""
    if topic.startswith(f"{VDA_PREFIX}/"):
        return VDA_VALIDATORS.get(topic.rsplit("/", 1)[-1])
    if not topic.startswith(f"{PREFIX}/"):
        return None
    parts = topic.split("/")
    if parts[-2] == "cmd":
        return VALIDATORS[CMD[parts[-1]]]
    return VALIDATORS[SUFFIX[parts[-1]]] if parts[-1] in SUFFIX else None


@dataclass(frozen=True)
class Received:
    topic: str
    body: Any  # the JSON, or the bytes when not JSON
    retain: bool
    at: float  # time.monotonic() on arrival


class Watcher:
    """A connected client: ``subscribe``, ``publish``, ``wait_for``; ``invalid`` lists
    every payload that failed its schema."""

    def __init__(
        self,
        broker: Broker,
        user: str,
        *,
        client_id: str,
        protocol: MQTTProtocolVersion = MQTTProtocolVersion.MQTTv5,
        tls: bool = False,
        secret: str | None = None,
    ) -> None:
        self.messages: list[Received] = []
        self.invalid: list[str] = []
        self._cond = threading.Condition()
        self._connected = threading.Event()
        self.refused: Any = None
        c = self.client = mqtt.Client(
            CallbackAPIVersion.VERSION2, client_id=client_id, protocol=protocol
        )
        c.username_pw_set(user, secret if secret is not None else password(user))
        port = broker.port
        if tls:
            c.tls_set(
                ca_certs=broker.certs("ca.crt"),
                certfile=broker.certs("client.crt"),
                keyfile=broker.certs("client.key"),
            )
            port = broker.tls_port
        c.on_connect = self._on_connect
        c.on_message = self._on_message
        self._subacks: dict[int, list[Any]] = {}
        c.on_subscribe = self._on_subscribe
        c.connect("127.0.0.1", port, 10)
        c.loop_start()

    def connected(self, timeout: float = 10) -> bool:
        return self._connected.wait(timeout)

    def _on_connect(self, c: Any, u: Any, flags: Any, reason: Any, props: Any) -> None:
        if reason.is_failure:
            self.refused = reason
        else:
            self._connected.set()
        with self._cond:
            self._cond.notify_all()

    def _on_subscribe(self, c: Any, u: Any, mid: int, codes: Any, props: Any) -> None:
        with self._cond:
            self._subacks[mid] = list(codes)
            self._cond.notify_all()

    def _on_message(self, c: Any, u: Any, m: mqtt.MQTTMessage) -> None:
        try:
            body: Any = json.loads(m.payload)
        except (ValueError, RecursionError):  # the tests' own hostile payloads
            body = bytes(m.payload)
        v = schema_of(m.topic)
        if v is not None and not isinstance(body, bytes):
            errors = [e.message for e in v.iter_errors(body)]
            if errors:
                self.invalid.append(f"{m.topic}: {errors} in {body}")
        with self._cond:
            self.messages.append(Received(m.topic, body, bool(m.retain), time.monotonic()))
            self._cond.notify_all()

    def subscribe(self, topic: str, qos: int = 1) -> list[Any]:
        """Subscribe and wait for the broker's answer (its reason codes)."""
        assert self.connected(), f"not connected: {self.refused}"
        rc, mid = self.client.subscribe(topic, qos)
        assert rc == 0 and mid is not None
        with self._cond:
            assert self._cond.wait_for(lambda: mid in self._subacks, 10)
            return self._subacks[mid]

    def publish(
        self,
        topic: str,
        body: Any,
        *,
        retain: bool = False,
        qos: int = 1,
        sender: str | None = None,
    ) -> None:
        """Publish and wait until it is written (qos 1: acknowledged)."""
        payload = body if isinstance(body, bytes) else json.dumps(body).encode()
        props = None
        if sender is not None:
            props = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
            props.UserProperty = ("sender", sender)
        info = self.client.publish(topic, payload, qos, retain, properties=props)
        info.wait_for_publish(10)

    def wait_for(
        self, match: Callable[[Received], bool], timeout: float = 10, since: int = 0
    ) -> Received:
        """The first message from index ``since`` that ``match``es, waiting up to ``timeout``."""
        found: list[Received] = []

        def seen() -> bool:
            found[:] = [m for m in self.messages[since:] if match(m)][:1]
            return bool(found)

        with self._cond:
            if not self._cond.wait_for(seen, timeout):
                tail = [(m.topic, m.body) for m in self.messages[-5:]]
                raise AssertionError(f"no such message within {timeout} s; last: {tail}")
        return found[0]

    def mark(self) -> int:
        with self._cond:
            return len(self.messages)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def topic_is(topic: str) -> Callable[[Received], bool]:
    return lambda m: m.topic == topic


ROVER = {
    "buses": {
        "robot": {
            "interface": "virtual",
            "channel": "mqtt-rover",
            "bitrate": 500000,
            "simulate": {
                "time_constant_ms": 60,
                "startup": {
                    "front": ["SERVO ON ON", "START ON ON"],
                    "rear": ["SERVO ON ON", "START ON ON"],
                },
            },
        }
    },
    "units": [
        {
            "name": n,
            "abh3_id": i,
            "host_id": 2,
            "protocol": "2023",
            "velocity_model": "motor",
            "command_rate_hz": 50,
            "limits": {"velocity": 3000},
            "broadcast": {"mask": 0x1F, "rate_hz": 20},
        }
        for n, i in (("front", 1), ("rear", 3))
    ],
    "robots": [
        {
            "name": "rover",
            "track_m": 0.5,
            "diameter_m": 0.15,
            "gear_ratio": 10,
            "pulses_per_rev": 4096,
            "limits": {"linear_mps": 0.8, "angular_radps": 2.0},
            "wheels": [
                {"unit": "front", "axis": "A", "side": "left"},
                {"unit": "front", "axis": "B", "side": "right"},
                {"unit": "rear", "axis": "A", "side": "left"},
                {"unit": "rear", "axis": "B", "side": "right"},
            ],
        }
    ],
}


def config(tmp: Path, name: str, broker: Broker, /, **mqtt_settings: Any) -> Path:
    """A rover's YAML whose ``mqtt`` plugin connects as user ``name`` (its password in a
    file); ``mqtt_settings`` override the plugin's settings."""
    secret = tmp / f"{name}.password"
    secret.write_text(password(name) + "\n")
    doc = json.loads(json.dumps(ROVER))
    doc["buses"]["robot"]["channel"] = f"mqtt-{name}-{os.getpid()}"
    doc["plugins"] = {
        "mqtt": {
            "broker": broker.url,
            "name": name,
            "username": name,
            "password_file": str(secret),
            "keepalive_s": 2,
            "state_rate_hz": 5,
            **mqtt_settings,
        }
    }
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


@dataclass
class Supervisor:
    proc: subprocess.Popen[bytes]
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")


@contextlib.contextmanager
def supervisor(path: Path, *extra: str) -> Iterator[Supervisor]:
    """``abh3 run PATH --headless`` in a process of its own (its log in ``PATH.log``); on
    leaving, SIGTERM unless it ended already."""
    log_path = path.with_suffix(".log")
    with log_path.open("wb") as log:
        proc = subprocess.Popen(
            [*RUN, str(path), "--headless", "--no-socket", "--status-interval", "0", *extra],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
        )
    run = Supervisor(proc, log_path)
    try:
        yield run
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)


HOST = 2  # ROVER's units' host_id: a DP0 command is 0x00EF<drive><host>
START_BITS = (1 << 1) | (1 << 9)  # AY_START, BX_START of the 2023 input word


def dp0_commands(recording: Path, since: float) -> list[tuple[float, int, bool]]:
    """The supervisor's DP0 commands from ``since`` (``time.time()``) in ``--record``'s
    candump log (flushed as it runs: readable while it does): (time, drive, START on
    either axis)."""
    out: list[tuple[float, int, bool]] = []
    # candump: (t) channel ID#DATA T|R; a last line not yet ended is not read (being written)
    for line in recording.read_text().split("\n")[:-1]:
        stamp, _, frame, *_ = line.split()
        t = float(stamp.strip("()"))
        ident, data = frame.split("#")
        arbitration_id, payload = int(ident, 16), bytes.fromhex(data)
        ours = arbitration_id & 0xFF == HOST  # sent by the supervisor, not a drive's reply
        if t < since or arbitration_id >> 16 & 0xFF != 0xEF or not ours or len(payload) != 8:
            continue
        inputs = int.from_bytes(payload[4:8], "little")
        out.append((t, arbitration_id >> 8 & 0xFF, bool(inputs & START_BITS)))
    return out


def stop_frames(recording: Path, since: float) -> dict[int, float]:
    """Each drive's first DP0 command from ``since`` with START off on both axes."""
    first: dict[int, float] = {}
    for t, drive, started in dp0_commands(recording, since):
        if drive not in first and not started:
            first[drive] = t
    return first
