"""A flood on any command topic never holds a valid e-stop back (docs/fleet.md, "a flooding
fleet"): a real Mosquitto on loopback, the supervisor as ``abh3 run --headless``.

Once, a second of ``{not json`` (3,128 messages) to ``{prefix}/all/cmd/estop`` held the
robot's e-stop 29.5 s behind it — the e-stop connection was read at most 100 messages a
second, refused or not — and it was then refused as stale. Here each flood is followed by
a valid, fresh e-stop, and its latency (publish → the robot's ``estop_latched`` event) is
held against a control: the same e-stop with no flood, in the same run. Not an absolute
time: the bound is max(3 × control, control + 2 s), generous against a loaded machine,
where the old cap made it 30 s (and the e-stop stale, never latched).

The flood comes from a client of its own, paced over a second and closed by a QoS 1
message the broker acknowledges: the broker takes one connection's packets in order, so
by then the whole flood is queued for the supervisor, ahead of the e-stop. The test's own
observer subscribes to the robot's status and events only (not the flood).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from abh3_supervisor.fleet import payloads
from abh3_supervisor.fleet.topics import Topics
from tests.support.mosquitto import FLEET, Broker, running
from tests.support.mqtt_watch import Received, Watcher, config, supervisor

pytestmark = pytest.mark.wallclock
NAME = "flood"
FID = f"{NAME}-rover"
T = Topics(FID)
FLOOD_S = 1.0  # each flood is paced over this long, as the incident's


def bound(control: float) -> float:
    """How late an e-stop after a flood may latch, against one with no flood."""
    return max(3 * control, control + 2.0)


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Broker]:
    with running(tmp_path_factory.mktemp("broker"), {NAME: [FID]}) as b:
        yield b


def client(broker: Broker, name: str) -> Watcher:
    w = Watcher(broker, FLEET, client_id=f"t-{name}-{time.monotonic_ns()}")
    assert w.connected(), w.refused
    return w


def event(kind: str) -> Callable[[Received], bool]:
    return lambda m: m.topic == T.events and m.body["kind"] == kind


@dataclass
class Fleet:
    """The fleet's commands (one sender, its seq rising) and the robot's answers."""

    w: Watcher
    seq: int = 0

    def _body(self, path: str, *, stop: bool) -> tuple[str, dict[str, object]]:
        self.seq += 1
        now = time.time()
        if path == "vda":
            action = "startPause" if stop else "stopPause"
            body = payloads.vda_instant_actions(
                self.seq, now, manufacturer=T.manufacturer, fleet_id=FID, actions=[action]
            )
            return T.instant_actions, body
        kind = "estop" if stop else "estop_clear"
        return T.command(kind), payloads.estop_command(
            self.seq, now, sender="test-fleet", reason="flood test"
        )

    def estop(self, path: str, within: float) -> float:
        """A valid fresh e-stop on ``path`` (``cmd``: the robot's own e-stop topic;
        ``vda``: instantActions' startPause): seconds from its publish to the robot's
        ``estop_latched``; then cleared. Fails after ``within`` seconds."""
        topic, body = self._body(path, stop=True)
        mark = self.w.mark()
        sent = time.monotonic()
        self.w.publish(topic, body)
        latched = self.w.wait_for(event("estop_latched"), within, since=mark)
        self.w.wait_for(self.obeyed("estop"), 5, since=mark)  # this one latched it
        topic, body = self._body(path, stop=False)
        mark = self.w.mark()
        self.w.publish(topic, body)
        self.w.wait_for(event("estop_cleared"), 10, since=mark)
        self.w.wait_for(self.obeyed("estop_clear"), 5, since=mark)  # all said: none later
        return latched.at - sent

    def obeyed(self, kind: str) -> Callable[[Received], bool]:
        """The robot's word that it obeyed the last command sent, ``kind``."""
        seq = self.seq
        return lambda m: (
            event("fleet_command")(m)
            and m.body["data"]["kind"] == kind
            and m.body["data"]["seq"] == seq
        )


def flood(flooder: Watcher, topic: str, payload: bytes, count: int) -> None:
    """``count`` messages at QoS 0, paced over FLOOD_S; then one at QoS 1, acknowledged:
    the broker has queued all of them for the supervisor by then."""
    start = time.monotonic()
    for i in range(count):
        flooder.client.publish(topic, payload, 0)
        if i % 50 == 49:  # paced, as a flood from elsewhere comes
            time.sleep(max(0.0, start + FLOOD_S * (i + 1) / count - time.monotonic()))
    flooder.publish(topic, payload, qos=1)


def junk_twist() -> bytes:
    body = payloads.twist_command(1, time.time(), sender="flood", linear=0.0, angular=0.0)
    return payloads.encode(body)


def stale_estop() -> bytes:
    body = payloads.estop_command(1, time.time() - 60, sender="flood", reason="stale")
    return payloads.encode(body)


# name: (the flooded topic, its payload, how many in FLOOD_S, the e-stop's path after it)
FLOODS: dict[str, tuple[str, Callable[[], bytes], int, str]] = {
    # the incident: junk to everyone's e-stop, then one to this robot
    "junk on all's e-stop": (T.command("estop", everyone=True), lambda: b"{not json", 3128, "cmd"),
    # on the very topic of the e-stop: valid JSON, judged and refused as stale
    "stale e-stops on the robot's own": (T.command("estop"), stale_estop, 3000, "cmd"),
    # larger than 4 KiB: refused by size, read no further
    "oversized on the robot's clear": (T.command("estop_clear"), lambda: b"{" + b"x" * 8192, 800, "cmd"),
    # a VDA 5050 startPause is an e-stop: its connection is not capped either
    "junk on instantActions": (T.instant_actions, lambda: b"{not json", 3000, "vda"),
    # the twists' connection is capped (read 100 a second): their flood is its own
    "twists": (T.command("twist"), junk_twist, 3000, "cmd"),
}  # fmt: skip


def test_a_flood_on_any_command_topic_delays_no_valid_e_stop(
    broker: Broker, tmp_path: Path
) -> None:
    w = client(broker, "fleet")
    for topic in (T.status, T.events):  # not the commands: the test would read the flood
        w.subscribe(topic)
    flooder = client(broker, "flooder")
    fleet = Fleet(w)
    cfg = config(tmp_path, NAME, broker, allow_estop=True, allow_estop_clear=True)
    with supervisor(cfg) as run:
        w.wait_for(lambda m: m.topic == T.status and m.body["state"] == "online", 30)
        # the controls: the worse of three each, with no flood
        control = {path: max(fleet.estop(path, 10) for _ in range(3)) for path in ("cmd", "vda")}
        late: dict[str, float] = {}
        for name, (topic, payload, count, path) in FLOODS.items():
            flood(flooder, topic, payload(), count)
            allowed = bound(control[path])
            try:
                late[name] = fleet.estop(path, allowed + 5)
            except AssertionError as exc:  # never latched: say which flood, and the log's why
                why = [line for line in run.log().splitlines() if "stale" in line][-3:]
                raise AssertionError(f"after {name}: {exc}; {why}") from None
            assert late[name] <= allowed, (name, late, control)
        log = run.log()
    flooder.close()
    w.close()
    assert "could not be handled" not in log
    print(f"e-stop latency [s]: control {control}, after each flood {late}")
    assert not w.invalid
