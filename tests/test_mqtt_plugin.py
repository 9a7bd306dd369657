"""The bus never notices the broker: the ``mqtt`` plugin in a run of the plugin harness
(abh3_supervisor/plugin_testing.py, the simulator), its hooks called far faster than any
supervisor calls them, against a dead broker and against a flooding one. Counted, not
timed: every call returns, the outbox stays within its bound, what it dropped is counted
and said once, and the drives' exchanges go on."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from abh3_plugins.mqtt.plugin import MqttPlugin
from abh3_supervisor.fleet import payloads
from abh3_supervisor.fleet.topics import Topics
from abh3_supervisor.plugin_api import FlagChange, OwnerChange
from abh3_supervisor.plugin_testing import running
from tests.support.foreign_host import BusHost
from tests.support.mosquitto import FLEET, free_port, password
from tests.support.mosquitto import running as broker_running
from tests.support.mqtt_watch import Received, Watcher, topic_is
from tests.support.rig import TWO_UNITS

pytestmark = pytest.mark.wallclock
CALLS = 20_000
QUEUE = 100


def hammer(plugin: MqttPlugin, calls: int = CALLS) -> int:
    """Call the owner hook ``calls`` times (an event and a state check each); how many
    returned."""
    done = 0
    for i in range(calls):
        plugin.abh3_owner(OwnerChange("left", float(i), "a", "b"))
        done += 1
    return done


def read_states(plugin: MqttPlugin, calls: int = CALLS) -> int:
    """Call the flags hook ``calls`` times for a word that says nothing new: each reads
    the unit's whole state from the view and compares it (the work of every hook), and
    queues nothing; how many returned."""
    done = 0
    for i in range(calls):
        plugin.abh3_flags(FlagChange("left", float(i), "io", 0, 0))
        done += 1
    return done


def test_a_dead_broker_blocks_no_hook_and_the_outbox_stays_bounded() -> None:
    plugin = MqttPlugin()
    settings = {"broker": f"mqtt://127.0.0.1:{free_port()}", "queue": QUEUE, "name": "dead"}
    with running(TWO_UNITS, plugin, "mqtt", seconds=2.5, settings=settings) as run:
        assert run.wait_for(lambda r: len(r.feedback) >= 20)
        before = len(run.feedback)
        assert hammer(plugin) == CALLS
        link = plugin.links["left"]
        assert not link.connected.is_set()
        assert len(link.outbox) <= QUEUE
        assert link.outbox.dropped >= CALLS - QUEUE
        assert run.wait_for(lambda r: len(r.feedback) >= before + 20)  # the drives go on
    assert run.exit_code == 0, run.log
    said = [line for line in run.log if "does not keep up" in line]
    assert len(said) == 1 and "mqtt dead-left" in said[0]  # once, not per drop
    # each robot's four connections wait to reconnect, up to a second each to notice the
    # way out: told all at once, they end within abh3_stop's deadline, not one by one
    assert not any("abh3_stop" in line for line in run.log), run.log


def test_a_flooding_fleet_and_a_10_mb_message_block_no_hook(tmp_path: Path) -> None:
    fids = ["flood-left", "flood-right"]
    with broker_running(tmp_path / "broker", {"flood": fids}) as broker:
        secret = tmp_path / "pw"
        secret.write_text(password("flood"))
        settings = {
            "broker": broker.url,
            "name": "flood",
            "username": "flood",
            "password_file": str(secret),
            "protocol": "3.1.1",  # no maximum packet size: the 10 MB message does arrive
            "queue": QUEUE,
        }
        fleet = Watcher(broker, FLEET, client_id="t-flooder")
        assert fleet.connected()
        fleet.subscribe("abh3/v1/flood-left/events")
        plugin = MqttPlugin()
        with running(TWO_UNITS, plugin, "mqtt", seconds=4, settings=settings) as run:
            assert run.wait_for(lambda r: len(r.feedback) >= 20)
            fleet.wait_for(lambda m: m.topic.endswith("/events"))  # connected, subscribed
            t = Topics("flood-left")
            big = payloads.estop_command(1, time.time(), sender="f", reason="x" * 10_000_000)
            fleet.publish(t.command("estop"), big, qos=0)

            def flood() -> None:
                for seq in range(2, 3002):
                    body = payloads.estop_command(seq, time.time(), sender="f", reason="flood")
                    fleet.client.publish(t.command("estop"), json.dumps(body), 0)

            flooder = threading.Thread(target=flood)
            flooder.start()
            before = len(run.feedback)
            assert read_states(plugin) == CALLS
            flooder.join()
            assert len(plugin.links["left"].outbox) <= QUEUE
            refused = fleet.wait_for(
                lambda m: (
                    m.topic.endswith("/events")
                    and m.body["kind"] == "fleet_command_refused"
                    and m.body["data"].get("refused_unsaid", 0) > 0
                ),
                10,
            )
            assert refused.body["data"]["refused_unsaid"] > 0
            fleet.wait_for(lambda m: "allow_estop is false" in str(m.body))
            assert run.wait_for(lambda r: len(r.feedback) >= before + 20)
        fleet.close()
    assert run.exit_code == 0, run.log
    refusals = [line for line in run.log if "refused on" in line]
    assert 1 <= len(refusals) <= 4  # a line per robot and topic per 5 s, not per message
    assert not any("EMERGENCY STOP" in line for line in run.log)


def kind_of(topic: str, kind: str) -> Callable[[Received], bool]:
    return lambda m: m.topic == topic and m.body.get("kind") == kind


def test_an_e_stop_to_all_is_obeyed_by_every_robot_of_a_supervisor(tmp_path: Path) -> None:
    """Two robots (two connections) of one supervisor each receive ``all/cmd/estop``: each
    obeys it (the seq rule is per robot), the one gate latches once."""
    fids = ["pair-left", "pair-right"]
    with broker_running(tmp_path / "broker", {"pair": fids}) as broker:
        secret = tmp_path / "pw"
        secret.write_text(password("pair"))
        settings = {
            "broker": broker.url,
            "name": "pair",
            "username": "pair",
            "password_file": str(secret),
            "allow_estop": True,
        }
        fleet = Watcher(broker, FLEET, client_id="t-pair")
        assert fleet.connected()
        fleet.subscribe("abh3/v1/+/events")
        fleet.subscribe("abh3/v1/+/status")
        plugin = MqttPlugin()
        with running(TWO_UNITS, plugin, "mqtt", seconds=3, settings=settings) as run:
            for fid in fids:
                fleet.wait_for(topic_is(f"abh3/v1/{fid}/status"))
            body = payloads.estop_command(1, time.time(), sender="f", reason="all")
            fleet.publish(Topics("x").command("estop", everyone=True), body)
            for fid in fids:
                for kind in ("fleet_command", "estop_latched"):
                    fleet.wait_for(kind_of(f"abh3/v1/{fid}/events", kind))
        fleet.close()
    assert run.exit_code == 0, run.log
    assert not [m for m in fleet.messages if "refused" in str(m.body)]
    latched = [m.topic for m in fleet.messages if kind_of(m.topic, "estop_latched")(m)]
    assert sorted(latched) == [f"abh3/v1/{f}/events" for f in fids]  # the gate latched once


def test_another_host_on_a_drive_is_in_its_units_state_at_once(tmp_path: Path) -> None:
    """A hand-made second host commands left's drive on the simulator's virtual bus: the
    unit's state names it (address, frames) at once — not at the state rate, here one
    per 5 s — with a ``foreign_host`` event, and goes back to null once it is quiet."""
    fids = ["second-left", "second-right"]
    with broker_running(tmp_path / "broker", {"second": fids}) as broker:
        secret = tmp_path / "pw"
        secret.write_text(password("second"))
        settings = {
            "broker": broker.url,
            "name": "second",
            "username": "second",
            "password_file": str(secret),
            "state_rate_hz": 0.2,
        }
        fleet = Watcher(broker, FLEET, client_id="t-second")
        assert fleet.connected()
        fleet.subscribe("abh3/v1/+/units/+/state")
        fleet.subscribe("abh3/v1/second-left/events")
        left = Topics("second-left").state("left")
        plugin = MqttPlugin()
        with running(TWO_UNITS, plugin, "mqtt", seconds=10, settings=settings) as run:
            fleet.wait_for(lambda m: m.topic == left and m.body["online"] is True, 8)
            assert plugin.view is not None
            host = BusHost(plugin.view.config.buses["b"].channel, drive=1)
            loop = asyncio.new_event_loop()
            sending = threading.Thread(target=loop.run_until_complete, args=(host.run(),))
            mark, started = fleet.mark(), time.monotonic()
            sending.start()
            try:
                named = fleet.wait_for(
                    lambda m: m.topic == left and m.body["foreign_host"] is not None, 3, mark
                )
            finally:
                loop.call_soon_threadsafe(host.leave)
                sending.join(5)
                loop.close()
            assert named.body["foreign_host"]["address"] == 2  # the seed's host: a copy of us
            assert named.body["foreign_host"]["frames"] >= 1
            assert named.at - started < 1.0  # at once: the state's rate is one per 5 s
            heard = fleet.wait_for(kind_of(Topics("second-left").events, "foreign_host"), 3, mark)
            assert heard.body["data"]["address"] == 2
            quiet = fleet.wait_for(
                lambda m: m.topic == left and m.body["foreign_host"] is None, 8, fleet.mark()
            )
            assert quiet.body["estop"] is False  # a second host stops the robot, not the gate
        fleet.close()
    assert run.exit_code == 0, run.log
    right = [m for m in fleet.messages if m.topic == Topics("second-right").state("right")]
    assert right and all(m.body["foreign_host"] is None for m in right)
    assert not fleet.invalid
