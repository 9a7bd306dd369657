"""The journal: what the loop writes once and every watcher reads at its own pace."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.journal import Journal
from abh3_supervisor.core.supervisor import Notice, Supervisor
from abh3_supervisor.scheduler.core import FeedbackEvent
from tests.support.rig import Rig
from tests.support.threads import switching_often


def test_a_reader_gets_what_was_written_since_it_came_in_order() -> None:
    journal = Journal(8)
    journal.write("before")
    reader = journal.reader()
    for i in range(5):
        journal.write(i, sample=("s", i))
    assert [(e[1], e[2]) for e in reader.read()] == [(i, ("s", i)) for i in range(5)]
    assert reader.read() == [] and reader.missed == 0
    journal.write("next")
    assert [e[1] for e in reader.read()] == ["next"]


def test_a_reader_that_falls_a_ring_behind_counts_what_it_missed() -> None:
    journal = Journal(8)
    reader = journal.reader()
    for i in range(20):
        journal.write(i)
    assert [e[1] for e in reader.read()] == list(range(12, 20))  # the last 8
    assert reader.missed == 12
    journal.write(20)
    assert [e[1] for e in reader.read()] == [20] and reader.missed == 12


def test_the_size_is_a_power_of_two() -> None:
    with pytest.raises(ValueError, match="power of two"):
        Journal(12)


@pytest.fixture
def switching() -> Iterator[None]:
    """Threads switch as often as the interpreter allows: races show at once."""
    with switching_often():
        yield


def test_a_reader_on_another_thread_sees_each_entry_once_or_counts_it_missed(
    switching: None,
) -> None:
    """The loop writes, a watcher reads on its own thread, without a lock: every number
    it is given is in order, each once, and the rest it counts as missed."""
    journal = Journal(64)
    reader = journal.reader()
    written = 200_000
    seen: list[int] = []
    done = threading.Event()

    def read() -> None:
        while not done.is_set():
            seen.extend(entry[1] for entry in reader.read())
        seen.extend(entry[1] for entry in reader.read())

    thread = threading.Thread(target=read)
    thread.start()
    for i in range(written):
        journal.write(i)
    done.set()
    thread.join()
    assert seen == sorted(set(seen))  # in order, none twice
    assert len(seen) + reader.missed == written
    assert seen[-1] == written - 1


CONFIG = """
buses: {b: {interface: virtual, channel: journal-test, simulate: true}}
units:
  - {name: u, abh3_id: 1, protocol: "2023", command_rate_hz: 100, broadcast: {mask: 0}}
"""


def test_every_reply_is_written_once_with_what_it_left_and_watchers_told_per_step() -> None:
    """A step's replies reach the journal, each with the feedback, setpoint and inputs
    after it, and the watchers are told once per step — not once per reply."""
    rig = Rig(parse_config(CONFIG, "c.yaml"))
    sup: Supervisor = rig.sup
    reader = sup.journal.reader()
    told: list[int] = []
    sup.watchers.append(lambda: told.append(sup.journal.seq))
    rig.run(0.5)
    entries = reader.read()
    replies = [e for e in entries if isinstance(e[1], FeedbackEvent)]
    assert len(replies) >= 40  # 100 Hz for half a second
    for _, event, (feedback, setpoint, inputs) in replies:
        assert feedback is not None and feedback.t == event.t
        assert setpoint is not None and isinstance(inputs, int)
    assert 0 < len(told) <= len({e[1].t for e in replies}) + 5  # per step, not per event
    assert told == sorted(set(told))  # each told of news, once


def test_an_event_outside_a_step_tells_the_watchers_at_once() -> None:
    rig = Rig(parse_config(CONFIG, "c.yaml"))
    sup: Supervisor = rig.sup
    told: list[object] = []
    reader = sup.journal.reader()
    sup.watchers.append(lambda: told.extend(e[1] for e in reader.read()))
    sup.notice("u", 30, "said by a command")
    assert [type(e) for e in told] == [Notice]
