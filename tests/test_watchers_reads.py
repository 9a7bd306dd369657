"""Issue 50: what plugin threads read while the bus loop changes it.

A plugin's threads (the ROS 2 bridge's ``/diagnostics`` thread, its hook worker) read other
hosts heard on the bus (core/foreign.py) and the round-trip statistics (scheduler/stats.py)
while the loop adds hosts, forgives them and records replies. A read that raised there
("dictionary changed size during iteration", an index past a list that shrank) was a plugin
failure; five of them disabled the bridge. And ``SupervisorView.health()`` handed plugins
the live Supervisor itself.

The races are made likely, not certain: the interpreter switches threads every
microsecond here (``sys.setswitchinterval``), and the reads and changes interleave for a
bounded number of iterations; no test depends on how long anything takes.
"""

from __future__ import annotations

import asyncio
import dataclasses
import enum
import gc
import threading
from collections.abc import Callable, Iterator

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.diagnostics import Health, HealthSnapshot, Status
from abh3_supervisor.core.foreign import Foreign, ForeignWatch, Heard
from abh3_supervisor.core.state import UnitState
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.plugin_host.view import SupervisorView
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.scheduler.core import BusScheduler
from abh3_supervisor.scheduler.stats import RTT_WINDOW, UnitStats
from tests.support.rig import TWO_UNITS, Rig
from tests.support.threads import switching_often

ROUNDS = 20_000  # loop-side changes per test; the reader reads as often as it gets to
WORD = bytes.fromhex("f401f40103300000")
REQUEST = frames.encode_request(0xEF00)


@pytest.fixture(autouse=True)
def _switch_often() -> Iterator[None]:
    with switching_often():
        yield


def _interleaved(change: Callable[[int], None], read: Callable[[], object]) -> int:
    """``change(i)`` for ROUNDS values of i on one thread (the loop's part) while another
    thread calls ``read()`` until the changes are done; every exception either raised is
    re-raised here. Returns how many reads there were."""
    done = threading.Event()
    failures: list[BaseException] = []
    reads = [0]

    def loop_side() -> None:
        try:
            for i in range(ROUNDS):
                change(i)
        except BaseException as exc:
            failures.append(exc)
        finally:
            done.set()

    def plugin_side() -> None:
        try:
            while not done.is_set() or reads[0] == 0:
                read()
                reads[0] += 1
        except BaseException as exc:
            failures.append(exc)
            done.set()

    threads = [threading.Thread(target=loop_side), threading.Thread(target=plugin_side)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if failures:
        raise failures[0]
    return reads[0]


def _feed(watch: ForeignWatch, i: int) -> None:
    """What the loop does with other hosts' frames: new hosts (sources), commands and
    reads of ours drives, a clear that forgives, quiet spells that begin new episodes."""
    now = i * 0.01 + (i // 500) * 2.0  # every 500 frames a quiet spell: new episodes
    source = 0x10 + i % 97
    if i % 3 == 0:
        watch.frame(ids.dp0_command_id(1, source), WORD, now)
    elif i % 3 == 1:
        watch.frame(ids.request_id(ids.ADDR_ALL, source), REQUEST, now)
    else:
        watch.unasked_reply(3, source, ids.dp0_reply_id(3, source), WORD, now)
    if i % 7 == 0:
        watch.forgive("left")


def test_other_hosts_read_from_a_plugin_thread_while_the_loop_adds_and_forgives() -> None:
    watch = ForeignWatch({1: "left", 3: "right"})

    def read() -> None:
        for unit in ("left", "right"):
            for record in watch.of(unit):
                record.text()
                record.to_json()
            watch.commanding(unit, 1e9)
        for record in watch.hosts.values():
            assert record.commanding in (True, False)

    assert _interleaved(lambda i: _feed(watch, i), read) > 0
    assert len(watch.hosts) == 2 * 97


def test_round_trip_percentiles_read_while_replies_come_are_whole() -> None:
    """p0 ≤ p50 ≤ p99 ≤ p100 of one read, each a sample: never an index past the window
    (the loop drops the oldest sample before it sorts the new one in)."""
    stats = UnitStats(100.0)
    for k in range(RTT_WINDOW):
        stats.on_reply(k * 0.01, 0.001 + (k % 10) * 0.001)

    def change(i: int) -> None:
        stats.on_reply(20.0 + i * 0.01, 0.0005 if i % 2 else 0.05 + i * 1e-6)

    def read() -> None:
        p0, p50, p99, p100 = stats.rtts_ms(0, 50, 99, 100)
        assert p0 is not None and p50 is not None and p99 is not None and p100 is not None
        assert p0 <= p50 <= p99 <= p100
        assert stats.rtt_ms(100) is not None

    assert _interleaved(change, read) > 0


def test_health_and_foreign_hosts_read_from_a_plugin_thread_while_the_loop_changes_them() -> None:
    """What the ROS 2 bridge's diagnostics read, through the view it gets."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.run(0.5)
    scheduler = next(iter(rig.sup.schedulers.values()))
    watch = scheduler.foreign
    stats = scheduler.slots["left"].stats
    loop = asyncio.new_event_loop()
    loop.close()  # nobody runs it: the view reads on the caller's thread
    view = SupervisorView(rig.sup, loop, "probe")

    def change(i: int) -> None:
        _feed(watch, i)
        stats.on_reply(rig.timeline.now, 0.001 + (i % 50) * 1e-4)

    def read() -> None:
        statuses = view.health().statuses()
        assert {s.name for s in statuses} >= {"abh3_supervisor: unit left"}
        for unit in ("left", "right"):
            view.foreign_hosts(unit)

    assert _interleaved(change, read) > 0
    left = {s.name: s for s in view.health().statuses()}["abh3_supervisor: unit left"]
    assert ("foreign host", "0x10") in left.values  # the hosts heard: said, read from here
    assert [h.source for h in view.foreign_hosts("left")][:1] == [0x10]


# ------------------------------------------------------------------ health() is a copy

LIVE = (Supervisor, UnitState, BusScheduler, UnitStats, ForeignWatch, Foreign, Heard, Health)
PLAIN = (str, bytes, int, float, bool, type(None), enum.Enum)


def _reachable(root: object) -> Iterator[object]:
    """Every object reachable from ``root`` through its attributes and items (the
    garbage collector's referents), but for classes and functions (each object refers
    to its class)."""
    seen: set[int] = set()
    todo = [root]
    while todo:
        obj = todo.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, type) or callable(obj):  # a record's class: not its data
            continue
        yield obj
        if not isinstance(obj, PLAIN):
            todo.extend(gc.get_referents(obj))


def test_the_views_health_is_a_snapshot_of_plain_values_with_nothing_live_in_it() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.run(0.5)
    loop = asyncio.new_event_loop()
    loop.close()
    view = SupervisorView(rig.sup, loop, "probe")
    health = view.health()
    assert isinstance(health, HealthSnapshot)
    found = list(_reachable(health))
    live = [type(o).__name__ for o in found if isinstance(o, LIVE)]
    assert live == []
    mutable = [type(o).__name__ for o in found if isinstance(o, list | dict | set | bytearray)]
    assert mutable == []
    assert all(isinstance(o, (*PLAIN, tuple, Status, HealthSnapshot)) for o in found), {
        type(o).__name__ for o in found
    }
    with pytest.raises(dataclasses.FrozenInstanceError):
        health.t = 0.0  # type: ignore[misc]
    # what the ROS 2 bridge publishes: every bus, unit and robot, as the live Health says
    names = [s.name for s in Health(rig.sup).statuses(rig.timeline.now)]
    assert [s.name for s in health.statuses()] == names
    assert health.t == pytest.approx(rig.timeline.now)
    rig.run(0.5)
    assert view.health().t > health.t  # a new one each call; the one taken never changes
    assert health.statuses() == list(health.report)
