"""The fleet contract's pure side (abh3_supervisor/fleet/, docs/fleet.md): every payload
we build validates against our JSON Schemas, our VDA 5050 messages against the official
schemas (tests/data/vda5050/, release 2.1.0), and commands are judged as documented;
the plugin's outbox is bounded and its settings are checked as every section is."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from abh3_plugins.mqtt.outbox import Message, Outbox
from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import ConfigError, PluginError
from abh3_supervisor.fleet import payloads, schemas
from abh3_supervisor.fleet.ids import client_id, fleet_id
from abh3_supervisor.fleet.payloads import Refused, SeqGuard, UnitReport
from abh3_supervisor.fleet.topics import Topics, Where, command_kind, robot_of, where
from abh3_supervisor.plugin_host.host import PluginHost
from tests.support.mqtt_watch import VALIDATORS, VDA_VALIDATORS
from tests.support.rig import TWO_UNITS

ROOT = Path(__file__).resolve().parent.parent
NOW = 1_800_000_000.0


def valid(name: str, payload: dict[str, Any]) -> None:
    VALIDATORS[name].validate(json.loads(payloads.encode(payload)))


def test_the_schemas_are_draft_2020_12_with_the_contract_ids() -> None:
    for name in schemas.NAMES:
        schema = schemas.load(name)
        jsonschema.Draft202012Validator.check_schema(schema)
        assert schema["$id"] == f"abh3/v1/{name}"
        assert {"v", "time", "seq"} <= set(schema["required"])


def test_fleet_ids_client_ids_and_topics() -> None:
    fid = fleet_id("Line 3/agv#7", "rover")
    assert fid == "Line_3_agv_7-rover" and client_id(fid) == "abh3-Line_3_agv_7-rover"
    t = Topics(fid)
    assert t.status == f"abh3/v1/{fid}/status"
    assert t.state("front") == f"abh3/v1/{fid}/units/front/state"
    assert t.command("estop", everyone=True) == "abh3/v1/all/cmd/estop"
    assert t.connection == f"uagv/v2/waco-giken-abh3/{fid}/connection"
    assert command_kind(t.command("twist")) == (fid, "twist")
    assert command_kind(t.events) is None and command_kind("abh3/v1/x/cmd/reboot") is None
    assert robot_of(t.state("front")) == (fid, "units/front/state")
    with pytest.raises(ValueError, match="no command"):
        t.command("reboot")


def test_a_reader_sorts_every_topic_back() -> None:
    t = Topics("plant-a")
    assert where(t.status) == Where("plant-a", "status")
    assert where(t.state("left")) == Where("plant-a", "state", "left")
    assert (where(t.events), where(t.health)) == (Where("plant-a", "events"), Where("plant-a", "health"))  # fmt: skip
    assert where(t.command("estop", everyone=True)) == Where("all", "command")
    assert where(t.command("twist")) == Where("plant-a", "command")
    for other in ("abh3/v1/plant-a/cmd/reboot", "abh3/v1/plant-a/units//state", "abh3/v1//status"):
        place = where(other)
        assert place is not None and place.kind == "unknown", other
    assert where(t.connection) is None and where("abh3/v2/plant-a/status") is None
    assert where("site/abh3/v1/x/status", "site/abh3/v1") == Where("x", "status")


def test_every_payload_we_build_validates() -> None:
    seq = payloads.Sequence()
    assert [seq("a"), seq("a"), seq("b")] == [1, 2, 1]
    common = {"fleet_id": "h-rover", "robot": "rover"}
    for state in payloads.STATES:
        valid(
            "status",
            payloads.status(
                1, NOW, **common, state=state, host="h", pid=1, version="0.1.0", units=["a"]
            ),
        )
    never = UnitReport("front", None)
    full = UnitReport(
        "front",
        True,
        (True, False),
        (True, True),
        (300.0, -20.0),
        (299.5, float("nan")),  # a non-finite reading is said as null, never NaN
        ("OVERCURRENT",),
        ("OVERLOAD",),
        "mqtt:h-rover",
        True,
        "ok",
        (5, 12),
        0.01,
    )
    for report in (never, full):
        valid("unit_state", payloads.unit_state(2, NOW, **common, report=report))
    assert payloads.unit_state(2, NOW, **common, report=full)["measured"]["b"] is None
    event = payloads.event(
        3, NOW, fleet_id="h-rover", robot="rover", unit=None, kind="estop_latched", text="x"
    )
    valid("event", event)
    bus = {"frames_sent": 1, "frames_received": 2, "send_errors": 0, "state": "ok"}
    for not_heard in (None, ["twist", "instant_actions", "estop"]):
        health = payloads.health(
            4,
            NOW,
            fleet_id="h-rover",
            robot="rover",
            buses={"b": bus},
            queued=0,
            dropped=3,
            reconnects=1,
            not_heard=not_heard,
        )
        valid("health", health)
    assert health["mqtt"]["not_heard"] == ["estop", "instant_actions", "twist"]
    valid("estop_command", payloads.estop_command(1, NOW, sender="scada", reason="door"))
    valid("twist_command", payloads.twist_command(1, NOW, sender="f", linear=0.1, angular=0))
    with pytest.raises(ValueError):
        payloads.encode({"x": float("inf")})


def test_our_vda5050_messages_validate_against_the_official_schemas() -> None:
    for state in payloads.STATES:
        msg = payloads.vda_connection(
            7, NOW, manufacturer="waco-giken-abh3", fleet_id="h-rover", state=state
        )
        VDA_VALIDATORS["connection"].validate(msg)
    assert msg["connectionState"] == "CONNECTIONBROKEN"
    assert payloads.iso(NOW + 0.25) == "2027-01-15T08:00:00.250Z"
    actions = payloads.vda_instant_actions(
        1, NOW, manufacturer="m", fleet_id="f", actions=["startPause", "stopPause"]
    )
    VDA_VALIDATORS["instantActions"].validate(actions)


def estop(**over: Any) -> bytes:
    body = {**payloads.estop_command(5, NOW, sender="scada", reason="door"), **over}
    return json.dumps(body).encode()


@pytest.mark.parametrize(
    ("raw", "retained", "why"),
    [
        (estop(), True, "retained"),
        (estop(time=NOW - 0.6), False, "stale"),
        (estop(time=NOW + 0.6), False, "from the future"),
        (estop(time=float("nan")), False, "not JSON"),  # NaN is not JSON: json.dumps writes it
        (b"\xff", False, "not JSON"),
        (b"[]", False, "not a JSON object"),
        (estop(v=2), False, "'v'"),
        (estop(seq=0), False, "counts from 1"),
        (estop(seq=True), False, "'seq': bool"),
        (estop(sender=None), False, "'sender'"),
        (estop(reason=7), False, "'reason'"),
        (estop(reason="x" * 10_000), False, "bytes"),  # larger than any command: unread
    ],
)
def test_commands_are_refused_when(raw: bytes, retained: bool, why: str) -> None:
    with pytest.raises(Refused, match=why):
        payloads.parse_command("estop", raw, now=NOW, timeout_s=0.5, retained=retained)


def test_a_good_command_and_its_sender() -> None:
    c = payloads.parse_command("estop", estop(), now=NOW + 0.1, timeout_s=0.5, retained=False)
    assert (c.kind, c.sender, c.seq, c.reason, c.extra) == ("estop", "scada", 5, "door", {})
    c = payloads.parse_command(
        "estop", estop(), now=NOW, timeout_s=0.5, retained=False, sender_property="fleet-1"
    )
    assert c.sender == "fleet-1" and c.extra == {"payload_sender": "scada"}
    twist = payloads.twist_command(1, NOW, sender="f", linear=0.2, angular=-0.1)
    c = payloads.parse_command(
        "twist", json.dumps(twist).encode(), now=NOW, timeout_s=0.5, retained=False
    )
    assert (c.linear, c.angular) == (0.2, -0.1)
    bad = json.dumps(twist).replace("0.2", "1e400").encode()  # valid JSON, inf once read
    with pytest.raises(Refused, match="finite"):
        payloads.parse_command("twist", bad, now=NOW, timeout_s=0.5, retained=False)


def test_seq_must_rise_per_sender_and_topic_unless_the_sender_started_again() -> None:
    guard = SeqGuard(0.5)

    def cmd(seq: int, t: float, sender: str = "a") -> payloads.Command:
        return payloads.Command("estop", sender, seq, t)

    guard.admit("x", cmd(3, NOW))
    with pytest.raises(Refused, match="seq 3 not above 3"):
        guard.admit("x", cmd(3, NOW + 0.1))
    with pytest.raises(Refused, match="seq 2"):
        guard.admit("x", cmd(2, NOW + 0.2))
    guard.admit("x", cmd(4, NOW + 0.2))
    guard.admit("y", cmd(1, NOW + 0.2))  # another topic, its own count
    guard.admit("x", cmd(1, NOW + 0.2, "b"))  # another sender, its own count
    guard.admit("x", cmd(1, NOW + 5))  # a new connection of sender a: seq from 1 again


def vda(**over: Any) -> bytes:
    body = payloads.vda_instant_actions(
        9, NOW, manufacturer="m", fleet_id="f", actions=["startPause", "stopPause", "pick"]
    )
    return json.dumps({**body, **over}).encode()


def test_instant_actions_map_to_the_e_stop_and_its_clearing() -> None:
    commands, skipped = payloads.parse_instant_actions(
        vda(), now=NOW, timeout_s=0.5, retained=False, manufacturer="m", fleet_id="f"
    )
    assert [c.kind for c in commands] == ["estop", "estop_clear"]
    assert commands[0].seq == 9 and commands[0].sender == "vda5050 m"
    assert len(skipped) == 1 and skipped[0].startswith("pick")
    for raw, retained, why in [
        (vda(), True, "retained"),
        (vda(serialNumber="g"), False, "serialNumber"),
        (vda(timestamp="2027-01-15T08:00:00"), False, "time zone"),
        (vda(timestamp="yesterday"), False, "ISO 8601"),
        (vda(timestamp="2020-01-15T08:00:00.000Z"), False, "stale"),
        (vda(actions=[{"actionType": "startPause", "actionId": "1"}]), False, "blockingType"),
    ]:
        with pytest.raises(Refused, match=why):
            payloads.parse_instant_actions(
                raw, now=NOW, timeout_s=0.5, retained=retained, manufacturer="m", fleet_id="f"
            )


def test_the_outbox_is_bounded_drops_states_first_and_counts() -> None:
    box = Outbox(10, "t")

    def msg(n: int) -> Message:
        return Message(f"t/{n}", b"", 0, False)

    for n in range(5):
        box.put(msg(n), lossy=False)  # events
    for n in range(100, 120):
        box.put(msg(n), lossy=True)  # states
    assert len(box) == 10 and box.dropped == 15
    taken = [m.topic for m in iter(lambda: box.take(0), None)]
    assert taken == [*(f"t/{n}" for n in range(5)), *(f"t/{n}" for n in range(115, 120))]
    for n in range(12):
        box.put(msg(n), lossy=False)  # nothing lossy left: the oldest kept one goes
    assert len(box) == 10 and box.dropped == 17


def test_the_last_message_goes_after_everything_even_what_is_put_after_it() -> None:
    """The orderly ``offline`` after the last states (put after it by the way out)."""
    box = Outbox(10, "t")
    box.put(Message("event", b"", 0, False), lossy=False)
    box.put_last(Message("offline", b"", 0, True))
    box.put(Message("state", b"", 0, False), lossy=True)
    assert len(box) == 3
    assert [m.topic for m in iter(lambda: box.take(0), None)] == ["event", "state", "offline"]


def problems(section: str) -> list[str]:
    cfg = parse_config(TWO_UNITS + f"plugins:\n  mqtt:\n{section}", "f.yaml")
    try:
        PluginHost(cfg)
    except ConfigError as exc:
        return list(exc.problems)
    return []


def test_settings_are_checked_with_file_line_and_key(tmp_path: Path) -> None:
    assert problems("    broker: mqtt://127.0.0.1:1883\n") == []
    bad = [
        ("    broker: http://x\n", "plugins.mqtt.broker: 'http://x': write mqtt://"),
        ("    broker: mqtt://u:p@x:1883\n", "no credentials in the URL"),
        ("    allow_estop_clear: true\n", "plugins.mqtt.allow_estop_clear: needs allow_estop"),
        ("    alow_estop: true\n", "did you mean 'allow_estop'"),
        ("    protocol: 4\n", "plugins.mqtt.protocol"),
        ("    qos: {state: 3}\n", "plugins.mqtt.qos.state: 3 is out of range"),
        ("    tls: {ca: /nope.pem}\n    broker: mqtts://x\n", "plugins.mqtt.tls.ca: '/nope.pem'"),
        ("    tls: {ca: /etc/hostname}\n", "TLS settings need an mqtts:// broker"),
        ("    username: u\n    password_file: /nope\n", "plugins.mqtt.password_file"),
        ("    password_env: X\n", "plugins.mqtt.username: a password needs a username"),
        ("    password_env: 'A B'\n    username: u\n", "not an environment variable"),
        ("    on_broker_loss: halt\n", "plugins.mqtt.on_broker_loss"),
        ("    name: a/b\n", "plugins.mqtt.name"),
        ("    topic_prefix: 'abh3/#'\n", "plugins.mqtt.topic_prefix"),
        ("    attach: http://x\n", "plugins.mqtt.attach"),
        ("    manufacturer: 'acme/#'\n", "plugins.mqtt.manufacturer: 'acme/#': only letters"),
        ("    allow_commands: true\n    protocol: '3.1.1'\n", "allow_commands: needs protocol: 5"),
        (
            "    username: u\n    password_env: X\n    password_file: /etc/hostname\n",
            "plugins.mqtt.password_file: give password_env or password_file, not both",
        ),
    ]
    for section, expect in bad:
        found = problems(section)
        assert any(expect in p and p.startswith("f.yaml:") for p in found), (section, found)


def test_a_password_that_cannot_be_had_is_said_with_its_setting(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from abh3_plugins.mqtt.settings import Settings

    monkeypatch.delenv("ABH3_NOT_SET", raising=False)
    unset = Settings(password_env="ABH3_NOT_SET", secret_at="f.yaml:7: plugins.mqtt.password_env")
    with pytest.raises(PluginError) as env:
        unset.password()
    assert str(env.value) == (
        "f.yaml:7: plugins.mqtt.password_env: the environment variable ABH3_NOT_SET is not set"
    )
    missing = Settings(password_file=str(tmp_path / "gone"), secret_at="f.yaml:8: k")
    with pytest.raises(PluginError, match=r"^f.yaml:8: k: .*gone: No such file or directory$"):
        missing.password()


def test_abh3_check_never_prints_the_password(tmp_path: Path) -> None:
    secret = tmp_path / "pw"
    secret.write_text("s3cr3t-pw\n")
    cfg = tmp_path / "c.yaml"
    text = (ROOT / "configs" / "fleet.yaml").read_text()
    text = text.replace("password_env: ABH3_MQTT_PASSWORD", f"password_file: {secret}")
    cfg.write_text(text)
    env = {"ABH3_MQTT_PASSWORD": "s3cr3t-env", "PATH": "/usr/bin:/bin"}
    for path in (ROOT / "configs" / "fleet.yaml", cfg):
        out = subprocess.run(
            [sys.executable, "-m", "abh3_supervisor", "check", str(path)],
            capture_output=True,
            text=True,
            env=env,
            cwd=ROOT,
        )
        assert out.returncode == 0, out.stderr
        assert "s3cr3t" not in out.stdout + out.stderr


def test_without_paho_check_says_which_extra_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "paho" else real(name, *a)
    )
    found = problems("    broker: mqtt://127.0.0.1:1883\n")
    assert any("needs paho-mqtt: pip install 'abh3-supervisor[mqtt]'" in p for p in found), found
