"""Fault paths: what the simulated drive does, not only what the log says (issue 11)."""

from __future__ import annotations

import logging

from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.scheduler.core import GapEvent, MalformedEvent
from abh3_supervisor.supervisor import Notice
from tests.conftest import Rig

SCHEDULER = 0  # the Rig adds the scheduler first, the simulated drives second


def drive_both(rig: Rig) -> None:
    for unit, vel in (("left", "VEL 300 0"), ("right", "VEL 200 200")):
        for text in ("SERVO ON ON", "START ON ON", vel):
            assert rig.sup.apply_text(unit, text) == ""


def speeds(rig: Rig) -> list[float]:
    return [abs(v) for unit in ("left", "right") for v in rig.drive(unit).vel]


def test_a_send_outage_longer_than_the_drive_timeout_never_restarts_the_drives(rig: Rig) -> None:
    drive_both(rig)
    rig.run(1.0)
    assert min(speeds(rig)[0:2]) > 100 and min(speeds(rig)[2:]) > 100  # moving
    outage = rig.timeline.now
    rig.timeline.refuse_sends(SCHEDULER, outage, outage + 0.8)  # within the 1 s offline time
    rig.run(0.8)
    # the drives stopped on their own 500 ms command-zero timeout …
    assert max(speeds(rig)) < 1.0
    assert all(rig.sup.units[u].online for u in ("left", "right"))  # never went offline
    rig.run(2.0)  # … and sending works again: they must stay stopped
    assert max(speeds(rig)) < 1.0
    gaps = [e for e in rig.events if isinstance(e, GapEvent)]
    assert [(e.unit, e.started) for e in gaps if e.started] == [("left", True), ("right", True)]
    assert all(outage + 0.45 <= e.t <= outage + 0.55 for e in gaps if e.started)
    assert any(
        isinstance(e, Notice) and "nothing moves until a new command" in e.message
        for e in rig.events
    )
    # a command given after the gap moves the drive again
    assert rig.sup.apply_text("left", "VEL 100 0") == ""
    rig.run(0.5)
    assert abs(rig.drive("left").vel[0]) > 50


def test_a_short_outage_within_the_drive_timeout_keeps_the_setpoint(rig: Rig) -> None:
    drive_both(rig)
    rig.run(1.0)
    rig.timeline.refuse_sends(SCHEDULER, rig.timeline.now, rig.timeline.now + 0.2)
    rig.run(1.0)
    assert not [e for e in rig.events if isinstance(e, GapEvent)]
    assert rig.sup.units["left"].setpoint.ay == 300.0
    assert min(speeds(rig)[0:2]) > 100


def test_wrong_length_replies_never_count(rig: Rig, caplog: object) -> None:
    rig.drive("left").silent = True
    reply = ids.dp0_reply_id(1, 2)
    for i in range(50):  # spoofed DLC-0 and short replies, a flood
        rig.sup.schedulers["b"].on_frame(reply, b"" if i % 2 else b"\x00" * 7, 0.001 * i)
        rig.sup.dispatch("b")
    rig.run(1.5)
    slot = rig.scheduler.slots["left"]
    assert slot.stats.malformed == 50 and slot.stats.replies == 0
    assert rig.sup.units["left"].online is False  # silent: never made online by junk
    assert rig.sup.units["left"].feedback is None
    notices = [e for e in rig.events if isinstance(e, Notice) and "malformed" in e.message]
    assert len(notices) == 1 and notices[0].level == logging.WARNING  # once per second
    assert len([e for e in rig.events if isinstance(e, MalformedEvent)]) == 50


def test_broadcast_7_proves_nothing(rig: Rig) -> None:
    rig.drive("left").silent = True
    rig.sup.schedulers["b"].on_frame(ids.broadcast_id(1, 5, 7), b"\x01", 0.0)
    rig.sup.dispatch("b")
    assert rig.sup.units["left"].online is None
    assert rig.sup.units["left"].status[7][1] == frames.Brd7(b"\x01")
