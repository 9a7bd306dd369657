"""The ``plugins.mqtt`` section of the YAML file, validated (docs/fleet.md, settings)."""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from abh3_supervisor.plugin_api import Config, PluginError, Section, fleet
from abh3_supervisor.plugin_api import schema as js

log = logging.getLogger("abh3_plugins.mqtt")
KEYS = {
    "broker",
    "protocol",
    "name",
    "topic_prefix",
    "manufacturer",
    "username",
    "password_env",
    "password_file",
    "tls",
    "keepalive_s",
    "state_rate_hz",
    "health_s",
    "qos",
    "allow_estop",
    "allow_estop_clear",
    "allow_commands",
    "command_timeout_ms",
    "priority",
    "on_broker_loss",
    "queue",
    "attach",
    "vda5050",
}
QOS_KEYS = ("status", "state", "events", "health", "commands")
QOS_DEFAULTS = {"status": 1, "state": 0, "events": 1, "health": 0, "commands": 1}
_PREFIX = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")
_ENV = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class Tls:
    ca: str | None = None  # None: the system's CAs
    cert: str | None = None
    key: str | None = None


@dataclass(frozen=True)
class Settings:
    host: str = "localhost"
    port: int = 1883
    tls: Tls | None = None  # None: plain TCP (mqtt://)
    protocol: str = "5"
    name: str = field(default_factory=fleet.default_name)
    prefix: str = fleet.PREFIX
    manufacturer: str = fleet.MANUFACTURER
    username: str | None = None
    password_env: str | None = None
    password_file: str | None = None
    secret_at: str = "plugins.mqtt"  # FILE:LINE: key of the password setting, for errors
    keepalive_s: int = 10
    state_rate_hz: float = 2.0
    health_s: float = 5.0
    qos: dict[str, int] = field(default_factory=lambda: dict(QOS_DEFAULTS))
    allow_estop: bool = False
    allow_estop_clear: bool = False
    allow_commands: bool = False
    command_timeout_s: float = 0.5
    priority: int = 0
    on_broker_loss: str = "continue"
    queue: int = 1000
    attach: str | None = None
    vda5050: bool = True

    @property
    def url(self) -> str:
        """The broker as the user wrote it, without credentials (logs)."""
        return f"{'mqtts' if self.tls else 'mqtt'}://{self.host}:{self.port}"

    def password(self) -> str | None:
        """The password, read now (never kept in the settings, never logged); a
        PluginError naming the setting when it cannot be had."""
        if self.password_env is not None:
            value = os.environ.get(self.password_env)
            if value is None:
                raise PluginError(
                    f"{self.secret_at}: the environment variable {self.password_env} is not set"
                )
            return value
        if self.password_file is not None:
            try:
                return Path(self.password_file).read_text("utf-8").rstrip("\r\n")
            except (OSError, UnicodeDecodeError) as exc:
                why = getattr(exc, "strerror", None) or exc
                raise PluginError(f"{self.secret_at}: {self.password_file}: {why}") from None
        return None


def _file(section: Section, key: str, base: Path) -> str | None:
    """A file to read, relative to the YAML's folder; it must be readable now."""
    if not section.has(key):
        return None
    text = section.text(key, "")
    if not text:
        return None
    path = Path(text).expanduser()
    path = path if path.is_absolute() else base / path
    if not os.access(path, os.R_OK) or not path.is_file():
        section.error(key, f"{text!r}: not a readable file ({path})")
    return str(path)


def parse(section: Section, config: Config) -> Settings:
    section.only(KEYS)
    d = Settings(name="-")
    base = Path(section.src.file).resolve().parent
    url = section.text("broker", "mqtt://localhost:1883")
    host, port, secure = _broker(section, url)
    t = section.sub("tls", {"ca", "cert", "key"})
    tls = Tls(_file(t, "ca", base), _file(t, "cert", base), _file(t, "key", base))
    if (tls.cert is None) != (tls.key is None):
        section.error("tls", "give both cert and key (the client certificate and its key)")
    if section.has("tls") and not secure:
        section.error("tls", f"{url}: TLS settings need an mqtts:// broker")
    q = section.sub("qos", set(QOS_KEYS))
    qos = {k: q.integer(k, v, 0, 2) for k, v in QOS_DEFAULTS.items()}
    env = section.text("password_env", "") or None
    if env is not None and section.data.get("password_file") is not None:
        section.error("password_file", "give password_env or password_file, not both")
    if env is not None and not _ENV.match(env):
        section.error("password_env", f"{env!r} is not an environment variable's name")
    elif env is not None and env not in os.environ:  # the run's environment, maybe not ours
        where = section.src.line((*section.path, "password_env"))
        log.warning(
            "%s:%d: plugins.mqtt.password_env: %s is not set here; abh3 run needs it",
            section.src.file,
            where,
            env,
        )
    prefix = section.text("topic_prefix", d.prefix)
    if not _PREFIX.match(prefix):
        section.error("topic_prefix", f"{prefix!r}: levels of [A-Za-z0-9_.-] joined by /")
    name = section.text("name", "") or fleet.default_name()
    if fleet.safe(name) != name:
        section.error("name", f"{name!r}: only letters, digits, _ . - (it is a topic level)")
    attach = section.text("attach", "") or None
    if attach is not None and not attach.startswith("ssh://"):
        section.error("attach", f"{attach!r}: an ssh://user@host/path/to.sock address")
    settings = Settings(
        host=host,
        port=port,
        tls=tls if secure else None,
        protocol=section.choice("protocol", d.protocol, ["5", "3.1.1"]),
        name=name,
        prefix=prefix,
        manufacturer=_manufacturer(section, d.manufacturer),
        username=section.text("username", "") or None,
        password_env=env,
        password_file=_file(section, "password_file", base),
        keepalive_s=section.integer("keepalive_s", d.keepalive_s, 1, 3600),
        state_rate_hz=section.number("state_rate_hz", d.state_rate_hz, 0.0, 50.0, lo_open=True),
        health_s=section.number("health_s", d.health_s, 0.0, 3600.0, lo_open=True),
        qos=qos,
        allow_estop=section.boolean("allow_estop", d.allow_estop),
        allow_estop_clear=section.boolean("allow_estop_clear", d.allow_estop_clear),
        allow_commands=section.boolean("allow_commands", d.allow_commands),
        command_timeout_s=section.integer("command_timeout_ms", 500, 10, 60_000) / 1000,
        priority=section.integer("priority", d.priority, -1000, 1000),
        on_broker_loss=section.choice("on_broker_loss", d.on_broker_loss, ["continue", "stop"]),
        queue=section.integer("queue", d.queue, 10, 1_000_000),
        attach=attach,
        vda5050=section.boolean("vda5050", d.vda5050),
        secret_at=_where(section, "password_env" if env is not None else "password_file"),
    )
    if settings.allow_commands and settings.protocol != "5":
        section.error(
            "allow_commands",
            "needs protocol: 5 — under MQTT 3.1.1 a command published retained reaches a "
            "connected robot without its retain flag, and motion never comes from one",
        )
    if settings.allow_estop_clear and not settings.allow_estop:
        section.error("allow_estop_clear", "needs allow_estop: true (clearing what it cannot set)")
    if (settings.password_env or settings.password_file) and settings.username is None:
        section.error("username", "a password needs a username")
    return settings


def _where(section: Section, key: str) -> str:
    path = (*section.path, key)
    return f"{section.src.file}:{section.src.line(path)}: {'.'.join(map(str, path))}"


def _manufacturer(section: Section, default: str) -> str:
    """The VDA 5050 ``manufacturer``: a topic level of its own (no ``/``, ``+``, ``#``)."""
    value = section.text("manufacturer", default)
    if not value or fleet.safe(value) != value:
        section.error("manufacturer", f"{value!r}: only letters, digits, _ . - (a topic level)")
    return value


def _broker(section: Section, url: str) -> tuple[str, int, bool]:
    """Host, port and TLS of ``mqtt://host[:port]`` or ``mqtts://host[:port]``."""
    parts = urlsplit(url)
    secure = parts.scheme == "mqtts"
    try:
        port = parts.port or (8883 if secure else 1883)
    except ValueError:
        port = 0
    if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname or port == 0:
        section.error("broker", f"{url!r}: write mqtt://host:1883 or mqtts://host:8883")
    elif parts.username or parts.password:
        section.error("broker", "no credentials in the URL: username, password_env/password_file")
    elif parts.path not in ("", "/"):
        section.error("broker", f"{url!r}: no path after host:port")
    return parts.hostname or "localhost", port or 1883, secure


def schema() -> dict[str, Any]:
    """The section's JSON Schema: the same keys, types and ranges as :func:`parse`."""
    d = Settings(name="-")
    qos = {k: js.integer(0, 2, f"QoS of {k}", v) for k, v in QOS_DEFAULTS.items()}
    return js.mapping(
        {
            "broker": js.text("mqtt://host:1883 or mqtts://host:8883", "mqtt://localhost:1883"),
            "protocol": js.choice(["5", 5, "3.1.1"], "MQTT version", d.protocol),
            "name": js.text("this supervisor's name in fleet ids (default: hostname)"),
            "topic_prefix": js.text("topics go under it", d.prefix),
            "manufacturer": js.text("VDA 5050 manufacturer", d.manufacturer),
            "username": js.text("the broker's user"),
            "password_env": js.text("environment variable holding the password"),
            "password_file": js.text("file holding the password (first line)"),
            "tls": js.mapping(
                {
                    "ca": js.text("CA certificate (PEM) of the broker"),
                    "cert": js.text("client certificate (PEM)"),
                    "key": js.text("client key (PEM)"),
                }
            ),
            "keepalive_s": js.integer(1, 3600, "keep-alive: the last will comes within ~1.5×", 10),
            "state_rate_hz": js.number(0.0, 50.0, "unit states per second", 2.0, lo_open=True),
            "health_s": js.number(0.0, 3600.0, "seconds between healths", 5.0, lo_open=True),
            "qos": js.mapping(qos),
            "allow_estop": js.boolean("obey the fleet's e-stop", False),
            "allow_estop_clear": js.boolean("obey the fleet's e-stop clear", False),
            "allow_commands": js.boolean("obey the fleet's twist", False),
            "command_timeout_ms": js.integer(10, 60_000, "older commands are refused", 500),
            "priority": js.integer(-1000, 1000, "in the input arbitration", 0),
            "on_broker_loss": js.choice(["continue", "stop"], "stop: e-stop on loss", "continue"),
            "queue": js.integer(10, 1_000_000, "messages waiting for the network", 1000),
            "attach": js.text("ssh://user@host/path/to.sock for status.attach"),
            "vda5050": js.boolean("VDA 5050 connection and instantActions", True),
        }
    )
