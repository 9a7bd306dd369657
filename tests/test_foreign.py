"""Another host on our drives (core/foreign.py): the detector on hand-built frames, the
scheduler's rule for replies we did not ask for, and the supervisor's stop on the fake
clock (a :class:`Timeline` with a hand-made second host)."""

from __future__ import annotations

import logging

import pytest

from abh3_supervisor.clients.control import status_lines
from abh3_supervisor.clients.mirror import Mirror
from abh3_supervisor.clients.tui import overview
from abh3_supervisor.clients.tui.model import detail_fields
from abh3_supervisor.config import parse_config
from abh3_supervisor.core import diagnostics
from abh3_supervisor.core.diagnostics import Level
from abh3_supervisor.core.foreign import QUIET_S, Evidence, ForeignWatch, evidence
from abh3_supervisor.core.supervisor import Notice
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.scheduler.core import BusScheduler, ForeignEvent
from abh3_supervisor.service.snapshot import supervisor_state
from tests.support.foreign_host import TimelineHost
from tests.support.rig import TWO_UNITS, Rig, set_velocity
from tests.support.robots import TWO_DRIVES
from tests.support.safe_word import is_safe_word

DRIVES = {1: "left", 3: "right"}
WORD = frames.encode_dp0_command(500, 500, 0x3003)
TP_RTS = bytes([0x10, 20, 0, 3, 0xFF, 0x00, 0xEF, 0x00])


# ------------------------------------------------------------ the detector alone


@pytest.mark.parametrize("host", [2, 0x05, 0xFE])
def test_any_dp0_command_to_our_drive_is_another_hosts_whatever_its_source(host: int) -> None:
    """We never hear our own frames: a command to our drive, from our own address too."""
    assert evidence(ids.dp0_command_id(1, host), DRIVES) == (Evidence.COMMAND, 1, host)
    assert evidence(ids.dp0_command_id(1, host, priority=6), DRIVES) == (
        Evidence.COMMAND,
        1,
        host,
    )


def test_a_parameter_session_to_our_drive_commands_and_a_request_reads() -> None:
    cm = ids.CanId(7, ids.PF_TP_CM, 3, 9).to_int()
    dt = ids.CanId(7, ids.PF_TP_DT, 3, 9).to_int()
    assert evidence(cm, DRIVES) == (Evidence.SESSION, 3, 9)
    assert evidence(dt, DRIVES) == (Evidence.SESSION, 3, 9)
    assert evidence(ids.request_id(3, 9), DRIVES) == (Evidence.REQUEST, 3, 9)
    assert evidence(ids.request_id(ids.ADDR_ALL, 9), DRIVES) == (Evidence.REQUEST, 0xFF, 9)


def test_frames_of_our_drives_and_to_other_nodes_are_no_evidence() -> None:
    assert evidence(ids.dp0_reply_id(1, 2), DRIVES) is None  # our drive's reply
    assert evidence(ids.broadcast_id(1, 5, 0), DRIVES) is None
    assert evidence(ids.CanId(7, ids.PF_TP_CM, 2, 1).to_int(), DRIVES) is None  # drive → us
    assert evidence(ids.dp0_command_id(7, 2), DRIVES) is None  # a drive not ours
    dp1 = ids.dp0_command_id(1, 2) | 1 << 24  # data page 1: no ABH3 frame
    assert evidence(dp1, DRIVES) is None


def test_a_host_using_one_of_our_drives_addresses_is_still_another_host() -> None:
    """Drives never address each other: a command to drive 1 from "3" is a host's (a
    second supervisor set up with host_id 3, a script that picked a drive's address)."""
    assert evidence(ids.dp0_command_id(1, 3), DRIVES) == (Evidence.COMMAND, 1, 3)
    assert evidence(ids.CanId(7, ids.PF_TP_CM, 3, 1).to_int(), DRIVES) == (
        Evidence.SESSION,
        3,
        1,
    )


def test_one_report_per_episode_and_a_new_one_after_quiet() -> None:
    watch = ForeignWatch(DRIVES)
    began = watch.frame(ids.dp0_command_id(1, 2), WORD, 10.0)
    assert [(r.source, r.drive, r.unit, r.commanding) for r in began] == [(2, 1, "left", True)]
    for k in range(1, 50):  # 50 Hz for a second: counted, not reported again
        assert watch.frame(ids.dp0_command_id(1, 2), WORD, 10.0 + k * 0.02) == []
    record = watch.of("left")[0]
    heard = record.heard[Evidence.COMMAND]
    assert (heard.count, heard.first) == (50, 10.0)
    assert heard.last == pytest.approx(10.98)
    assert "another host (0x02) commands drive 0x01 (unit left): 50 × DP0 command" in record.text()
    assert "00EF0102 [f4 01 f4 01 03 30 00 00]" in record.text()
    assert watch.commanding("left", 10.98 + QUIET_S) == [record]
    assert watch.commanding("left", 10.99 + QUIET_S) == []
    again = watch.frame(ids.dp0_command_id(1, 2), WORD, 12.5)  # back after a quiet spell
    assert len(again) == 1 and again[0].heard[Evidence.COMMAND].count == 1


def test_a_reader_is_reported_not_commanding_until_it_commands() -> None:
    watch = ForeignWatch(DRIVES)
    began = watch.frame(ids.request_id(ids.ADDR_ALL, 9), frames.encode_request(0xEF00), 1.0)
    assert sorted((r.unit, r.commanding) for r in began) == [("left", False), ("right", False)]
    assert "another host (0x09) reads drive 0x01" in watch.of("left")[0].text()
    assert watch.frame(ids.request_id(1, 9), frames.encode_request(0xEF00), 1.1) == []
    assert watch.commanding("left", 1.1) == []
    turned = watch.frame(ids.CanId(7, ids.PF_TP_CM, 1, 9).to_int(), TP_RTS, 1.2)
    assert [r.commanding for r in turned] == [True]  # news: it now stops the drive


def test_after_a_clear_the_next_command_is_news_even_within_the_episode() -> None:
    """A host quiet for QUIET_S is forgiven when its stop is cleared; if it commands again
    before its episode ended (it kept reading, or its frame was not yet read when the
    stop was cleared), that command stops the drive again."""
    watch = ForeignWatch(DRIVES)
    assert len(watch.frame(ids.dp0_command_id(1, 2), WORD, 1.0)) == 1
    reading = ids.request_id(1, 2), frames.encode_request(0xEF00)
    assert watch.frame(*reading, 1.9) == []  # it keeps reading: the episode goes on
    assert watch.commanding("left", 2.1) == []  # quiet as a commander: the stop may clear
    watch.forgive("left")
    assert [r.commanding for r in watch.of("left")] == [False]  # its reads stay on record
    again = watch.frame(ids.dp0_command_id(1, 2), WORD, 2.2)  # within the episode
    assert [r.commanding for r in again] == [True]  # news: the supervisor stops it again


# ------------------------------------------------------------ replies we did not ask for


def _scheduler(yaml: str = TWO_UNITS) -> BusScheduler:
    config = parse_config(yaml, "two.yaml")
    return BusScheduler(config.units_on("b"), 0.0)


def _foreign(s: BusScheduler) -> list[ForeignEvent]:
    return [e for e in s.drain_events() if isinstance(e, ForeignEvent)]


REPLY = bytes(8)


def test_a_reply_with_no_exchange_of_ours_is_reported_not_commanding() -> None:
    s = _scheduler()
    s.on_frame(ids.dp0_reply_id(1, 2), REPLY, 0.001)
    (event,) = _foreign(s)
    assert (event.unit, event.host.source, event.host.commanding) == ("left", 2, False)
    assert list(event.host.heard) == [Evidence.UNASKED_REPLY]
    assert event.host.who().startswith("drive 0x01 answers 0x02 unasked (another host")


def test_our_own_late_replies_after_a_reply_timeout_are_not_counted() -> None:
    s = _scheduler()
    slot = s.slots["left"]
    t = 0.0
    sent = 0
    while sent < 3:  # three exchanges in a row end unanswered (the drive is slow)
        out = s.poll(t)
        sent += sum(1 for i, _ in out if i == slot.command_id)
        t = s.next_deadline()
    assert slot.stats.timeouts == 2 and slot.dp0_sent_at is not None
    # then the three late replies come: the first answers the exchange in flight, the
    # others each stand for an exchange that timed out: ours, late
    for k in range(3):
        s.on_frame(ids.dp0_reply_id(1, 2), REPLY, t + 0.001 * k)
    assert _foreign(s) == []
    s.on_frame(ids.dp0_reply_id(1, 2), REPLY, t + 0.01)  # one more: no exchange explains it
    assert [e.host.heard[Evidence.UNASKED_REPLY].count for e in _foreign(s)] == [1]


def test_a_late_reply_after_a_stop_frame_sent_at_once_is_ours() -> None:
    s = _scheduler()
    s.poll(0.0)  # left's exchange in flight
    s.send_now("left", 0.005)  # the e-stop's frame replaces it
    s.on_frame(ids.dp0_reply_id(1, 2), REPLY, 0.006)
    s.on_frame(ids.dp0_reply_id(1, 2), REPLY, 0.007)
    assert _foreign(s) == []


def test_a_monitor_units_drive_is_not_ours_to_defend() -> None:
    s = _scheduler(TWO_UNITS.replace("name: left,", "name: left, role: monitor,"))
    s.on_frame(ids.dp0_command_id(1, 5), WORD, 0.001)
    assert _foreign(s) == []
    s.on_frame(ids.dp0_command_id(3, 5), WORD, 0.002)
    assert [e.unit for e in _foreign(s)] == ["right"]


# ------------------------------------------------------------ the supervisor, fake clock


def _moving(rig: Rig, unit: str) -> None:
    for text in ("SERVO ON ON", "START ON ON"):
        assert rig.sup.apply_text(unit, text) == ""
    set_velocity(rig.sup, unit, 100, 100, source=rig.own(unit))


def _ours(rig: Rig, address: int, since: float) -> list[tuple[float, bytes]]:
    """The DP0 commands the supervisor (the timeline's first node) sent to ``address``."""
    command = ids.dp0_command_id(address, 2)
    return [
        (f.end, f.data)
        for f in rig.timeline.frames
        if f.node == 0 and f.arbitration_id == command and f.end >= since
    ]


def test_a_second_host_stops_the_unit_at_once_and_keeps_it_stopped() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    host = TimelineHost(1, start=1.0, end=2.0)
    rig.timeline.add(host)
    rig.run(0.5)
    _moving(rig, "left")
    _moving(rig, "right")
    rig.run(0.45)
    assert rig.drive("left").cmd_raw == (500, 500)
    rig.run(0.1)  # the host's first frame at 1.0
    first = host.sent[0]
    ours = _ours(rig, 1, first)
    assert ours and ours[0][0] - first < 0.1  # the safe word within one period (50 Hz)
    layout = rig.sup.units["left"].layout
    assert all(is_safe_word(frames.unpack_dp0_command(d)[2], layout) for _, d in ours)
    assert all(frames.unpack_dp0_command(d)[:2] == (0, 0) for _, d in ours)
    # the other unit, a robot of its own, runs on
    assert rig.drive("right").cmd_raw == (500, 500)
    # refused while stopped: motion and SERVO, with the host named
    with pytest.raises(CommandError, match=r"another host \(0x02\) commands drive 0x01"):
        set_velocity(rig.sup, "left", 10, 10, source=rig.own("left"))
    with pytest.raises(CommandError, match="0x02"):
        rig.sup.set_inputs("left", layout.servo.both, layout.servo.both)
    # said once, as an ERROR naming the host and the frames, however many frames came
    rig.run(0.5)
    said = [e for e in rig.events if isinstance(e, Notice) and "another host" in e.message]
    assert len(said) == 1 and said[0].level == logging.ERROR
    assert "0x02" in said[0].message and "DP0 command" in said[0].message
    assert "00EF0102 [f4 01 f4 01" in said[0].message
    # status and diagnostics name the host
    state = supervisor_state(rig.sup, {})["units"]["left"]["foreign"]
    assert state["stopped"] and "0x02" in state["stopped"]
    (seen,) = state["hosts"]
    assert seen["source"] == 2 and seen["commanding"] and seen["frames"][0]["count"] > 10
    now, stopped = rig.timeline.now, rig.sup.gate.foreign.get("left")
    status = diagnostics.unit_status(rig.sup.units["left"], rig.scheduler, now, stopped)
    assert status.level is Level.ERROR and "another host (0x02)" in status.message
    assert ("foreign host", "0x02") in status.values
    # `abh3 status` and the TUI's overview say it on the unit's line
    snapshot = supervisor_state(rig.sup, {})
    (line,) = [x for x in status_lines(snapshot) if x.startswith("left:")]
    assert "STOPPED: another host (0x02) commands drive 0x01 (unit left)" in line
    mirror = Mirror.of(rig.config)
    mirror.apply(snapshot)
    shown = overview.render(mirror, list(mirror.units), 0, 200).plain
    assert "STOPPED: another host (0x02) commands drive 0x01 (unit left)" in shown
    assert any("× DP0 command" in f for f in detail_fields(mirror, "left"))
    # not cleared while the host is still heard, nor until it has been quiet for QUIET_S
    assert rig.sup.clear_emergency_stop("test") and rig.sup.gate.foreign
    rig.run(0.5 + QUIET_S / 2)  # the host left at 2.0
    assert host.left
    assert rig.sup.clear_foreign("test") and rig.sup.gate.foreign
    rig.run(QUIET_S / 2)
    assert rig.sup.clear_emergency_stop("test") == [] and not rig.sup.gate.foreign
    # nothing came back by itself: SERVO, START and motion must be given again
    assert rig.sup.units["left"].setpoint.ay == 0 and not rig.sup.units["left"].inputs & 0x3003
    _moving(rig, "left")
    rig.run(0.1)
    assert rig.drive("left").cmd_raw == (500, 500)


@pytest.mark.wire_allow("robot", reason="the other host drives one drive of the robot")
def test_a_second_host_on_one_drive_stops_its_whole_robot() -> None:
    rig = Rig(parse_config(TWO_DRIVES, "robot.yaml"))
    rig.timeline.add(TimelineHost(3, start=1.0, end=1.2))
    rig.run(1.1)
    assert set(rig.sup.gate.foreign) == {"l", "r"}
    assert "drive 0x03" in rig.sup.gate.foreign["l"]


def test_a_reader_is_reported_and_stops_nothing() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    reader = TimelineHost(
        1, start=1.0, end=1.5, host=9, word=frames.encode_request(0xEF00), request=True
    )
    rig.timeline.add(reader)
    rig.run(0.5)
    _moving(rig, "left")
    rig.run(1.0)
    assert not rig.sup.gate.foreign
    assert rig.drive("left").cmd_raw == (500, 500)
    said = [e for e in rig.events if isinstance(e, Notice) and "another host" in e.message]
    assert len(said) == 1 and said[0].level == logging.WARNING
    assert "another host (0x09) reads drive 0x01" in said[0].message


def test_a_parameter_session_of_another_host_stops_the_unit() -> None:
    """A tool writing the drive's parameters (J1939 transport) from its own address."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.run(0.5)
    _moving(rig, "left")
    rig.run(0.1)
    rig.scheduler.on_frame(ids.CanId(7, ids.PF_TP_CM, 1, 0x21).to_int(), TP_RTS, rig.timeline.now)
    rig.sup.dispatch("b")
    assert rig.sup.gate.foreign["left"] == "another host (0x21) commands drive 0x01 (unit left)"
    assert rig.sup.units["left"].setpoint.ay == 0
    rig.run(0.1)
    assert rig.drive("left").cmd_raw == (0, 0)
    assert is_safe_word(rig.drive("left").inputs, rig.sup.units["left"].layout)


@pytest.mark.parametrize("delay", [0.0, 0.03, 0.15, 0.4])
def test_a_supervisor_alone_hears_no_other_host_however_late_its_drives_answer(
    delay: float,
) -> None:
    """Replies later than the reply timeout (0.1 s), later than a period, or on time,
    through motion and an e-stop: every one is accounted for by an exchange of ours (the
    stop frames sent at once: test_a_late_reply_after_a_stop_frame_sent_at_once_is_ours)."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    for unit in ("left", "right"):
        rig.drive(unit).extra_delay = delay
    rig.run(0.5)
    _moving(rig, "left")
    rig.run(2.0)
    rig.sup.emergency_stop("test")
    rig.run(2.0)
    assert not [e for e in rig.events if isinstance(e, ForeignEvent)]
    assert rig.scheduler.slots["left"].stats.replies > 10
