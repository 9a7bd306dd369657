"""The per-bus scheduler on a fake clock, against the simulated drives. No sleeps."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import ids
from abh3_supervisor.protocol.classify import AddressBook, Kind, classify
from abh3_supervisor.scheduler.core import (
    BusScheduler,
    FeedbackEvent,
    HealthEvent,
    StatusEvent,
    turns,
)
from abh3_supervisor.scheduler.stats import RTT_WINDOW, UnitStats, percentile
from tests.support.rig import TWO_UNITS, Rig


def sent(rig: Rig, arbitration_id: int, since: float = 0.0) -> list[float]:
    return [
        f.start
        for f in rig.timeline.frames
        if f.arbitration_id == arbitration_id and f.start >= since
    ]


def test_command_rate_and_polls_follow_the_configuration(rig: Rig) -> None:
    rig.run(9.999)
    left = sent(rig, ids.dp0_command_id(1, 2))
    right = sent(rig, ids.dp0_command_id(3, 2))
    assert len(left) == 500 and len(right) == 500  # 50 Hz for 10 s
    polls = [f for f in rig.timeline.frames if f.arbitration_id == ids.request_id(1, 2)]
    assert len(polls) == 140  # 14 Hz
    book = AddressBook()
    asked = [classify(f.arbitration_id, f.data, True, book).payload for f in polls[:14]]
    assert [getattr(p, "broadcast", None) for p in asked] == [(5, n) for n in range(7)] * 2
    slot = rig.scheduler.slots["left"]
    assert slot.stats.timeouts == 0 and slot.stats.replies == 500
    assert abs(slot.stats.achieved_rate_hz(rig.timeline.now) - 50) < 0.5


def test_right_unit_polls_only_its_mask(rig: Rig) -> None:
    rig.run(2.0)
    book = AddressBook()
    decoded = [classify(f.arbitration_id, f.data, True, book) for f in rig.timeline.frames]
    # broadcast replies from drive 3 (right, mask 0x0f), all answers to our polls
    packets = {d.packet for d in decoded if d.kind is Kind.BROADCAST and d.abh3 == 3}
    assert packets == {0, 1, 2, 3}


def test_commands_go_before_polls_when_both_are_due() -> None:
    cfg = parse_config(
        "buses: {b: {}}\nunits: [{name: u, command_rate_hz: 10, broadcast: {rate_hz: 10}}]\n",
        "c.yaml",
    )
    sched = BusScheduler(cfg.units.values(), now=0.0)
    sched.slots["u"].next_poll = 0.0
    sched.slots["u"].refresh()  # as the scheduler does after every change to a deadline
    out = sched.poll(0.0)
    assert [ids.CanId.from_int(i).pf for i, _ in out] == [0xEF, 0xEA]


def test_replies_match_ignoring_priority_and_unsolicited_are_accepted() -> None:
    cfg = parse_config("buses: {b: {}}\nunits: [{name: u, priority: 6}]\n", "c.yaml")
    sched = BusScheduler(cfg.units.values(), now=0.0)
    (cmd_id, _), *_ = sched.poll(0.0)
    assert cmd_id == 0x18EF0102
    sched.on_frame(0x14EF0201, bytes(8), 0.001)  # any priority
    sched.on_frame(0x00EF0201, bytes(8), 0.002)  # nothing in flight: unsolicited
    events = sched.drain_events()
    feedback = [e for e in events if isinstance(e, FeedbackEvent)]
    assert [e.sent_at for e in feedback] == [0.0, None]
    assert sched.slots["u"].stats.unsolicited == 1
    assert any(isinstance(e, HealthEvent) and e.online for e in events)


def test_periodic_drive_frames_without_polling() -> None:
    cfg = parse_config(
        TWO_UNITS.replace(
            "simulate: true", "simulate: {broadcast_period_ms: 100, dp0_period_ms: 50}"
        ).replace("broadcast: {mask: 0x7f, rate_hz: 14}", "broadcast: {listen_only: true}"),
        "p.yaml",
    )
    rig = Rig(cfg)
    rig.run(1.0)
    assert not sent(rig, ids.request_id(1, 2))  # listen-only: never polled
    slot = rig.scheduler.slots["left"]
    assert slot.stats.broadcasts >= 60  # 7 packets every 100 ms
    assert slot.stats.unsolicited >= 15
    assert set(rig.sup.units["left"].status) == set(range(7))


def test_a_silent_unit_goes_offline_within_its_timeout_and_comes_back(rig: Rig) -> None:
    rig.run(1.0)
    rig.drive("right").silent = True
    silenced = rig.timeline.now
    rig.run(2.0)
    offline = [e for e in rig.events if isinstance(e, HealthEvent) and not e.online]
    assert [e.unit for e in offline] == ["right"]
    # the last reply came at most one period before silence: offline within timeout + period
    assert silenced < offline[0].t <= silenced + 1.0 + 0.02
    # the other unit's command rate holds while one is silent …
    left = sent(rig, ids.dp0_command_id(1, 2), since=silenced)
    assert len(left) == 100
    # … and the offline unit is only probed once per timeout, not at 50 Hz
    probes = sent(rig, ids.dp0_command_id(3, 2), since=offline[0].t)
    assert 1 <= len(probes) <= 2
    rig.drive("right").silent = False
    back = rig.timeline.now
    rig.run(1.5)
    online = [e for e in rig.events if isinstance(e, HealthEvent) and e.online and e.t > back]
    assert [e.unit for e in online] == ["right"] and online[0].t <= back + 1.0 + 0.01
    assert abs(rig.scheduler.slots["right"].stats.achieved_rate_hz(rig.timeline.now) - 50) < 1


def test_slow_replies_lower_the_rate_instead_of_being_mismatched(rig: Rig) -> None:
    rig.run(0.5)
    rig.drive("left").extra_delay = 0.030  # slower than the 20 ms command period
    start = rig.timeline.now
    rig.run(1.0)
    # one exchange in flight: each command waits for its reply, so round trips stay true …
    stats = rig.scheduler.slots["left"].stats
    assert stats.rtt_ms(50) == pytest.approx(30.2, abs=0.5)
    assert stats.timeouts == 0
    # … and the keepalive still runs, at the rate the drive allows
    assert 30 <= len(sent(rig, ids.dp0_command_id(1, 2), since=start)) <= 34
    assert rig.scheduler.slots["left"].online


def test_a_lost_reply_delays_the_next_command_by_at_most_the_reply_timeout(rig: Rig) -> None:
    rig.run(0.5)
    rig.drive("left").extra_delay = 10.0  # replies never come in time
    start = rig.timeline.now
    rig.run(1.0)
    times = sent(rig, ids.dp0_command_id(1, 2), since=start)
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) <= 0.100 + 1e-9  # reply_timeout_ms: far below the drive's 500 ms
    assert rig.scheduler.slots["left"].stats.timeouts >= 9


def test_a_unit_that_never_answers_is_reported_offline() -> None:
    rig = Rig(parse_config(TWO_UNITS, "t.yaml"))
    rig.drive("left").silent = True
    rig.run(1.5)
    offline = [e for e in rig.events if isinstance(e, HealthEvent) and not e.online]
    assert [(e.unit, e.t) for e in offline] == [("left", 1.0)]


def test_send_failure_frees_the_exchange() -> None:
    cfg = parse_config("buses: {b: {}}\nunits: [{name: u}]\n", "c.yaml")
    sched = BusScheduler(cfg.units.values(), now=0.0)
    (cmd_id, _), *_ = sched.poll(0.0)
    sched.on_send_failed(cmd_id)
    assert sched.slots["u"].dp0_sent_at is None and sched.slots["u"].stats.send_errors == 1


def test_monitor_units_only_request_feedback() -> None:
    rig = Rig(
        parse_config(TWO_UNITS.replace("name: right,", "name: right, role: monitor,"), "m.yaml")
    )
    rig.run(1.0)
    book = AddressBook(generations={})
    kinds = {
        classify(f.arbitration_id, f.data, True, book).kind
        for f in rig.timeline.frames
        if f.node == 0 and f.arbitration_id & 0xFF00 == 0x0300
    }
    assert kinds == {Kind.REQUEST}
    assert rig.sup.units["right"].feedback is not None


def test_status_on_demand_takes_the_next_poll_turn_once() -> None:
    """The seed's brd_num: a unit with no polling of its own answers requested packets."""
    cfg = parse_config(
        "buses: {b: {interface: virtual, channel: t, simulate: true}}\n"
        "units: [{name: u, broadcast: {mask: 0}}]\n",
        "c.yaml",
    )
    rig = Rig(cfg)
    rig.run(1.0)
    assert rig.scheduler.slots["u"].stats.polls_sent == 0  # mask 0: no polling at all
    for packet in (4, 4, 4, 0):  # a flood of the same request costs one frame
        rig.sup.request_status("u", packet)
    rig.run(0.5)
    answered = [e.packet for e in rig.events if isinstance(e, StatusEvent)]
    assert answered == [4, 0]
    assert rig.scheduler.slots["u"].stats.polls_sent == 2
    with pytest.raises(CommandError, match="not 0-6"):
        rig.sup.request_status("u", 7)


def test_requested_status_goes_between_the_regular_polls(rig: Rig) -> None:
    rig.run(1.0)
    rig.sup.request_status("right", 6)  # outside right's mask 0x0f: asked for explicitly
    rig.run(1.0)
    right = [e.packet for e in rig.events if isinstance(e, StatusEvent) and e.unit == "right"]
    assert right.count(6) == 1 and set(right) == {0, 1, 2, 3, 6}


@given(st.lists(st.floats(0.0, 0.2), min_size=1, max_size=2500), st.sampled_from([1, 50, 99]))
def test_rtt_percentiles_are_those_of_the_last_window_of_round_trips(
    rtts: list[float], q: int
) -> None:
    """Kept sorted as replies come (no sort per snapshot), equal to sorting the window."""
    stats = UnitStats(requested_rate_hz=50)
    for i, rtt in enumerate(rtts):
        stats.on_reply(float(i), rtt)
    window = rtts[-RTT_WINDOW:]
    assert stats.rtt_ms(q) == pytest.approx(percentile(window, q) * 1000)  # type: ignore[operator]
    assert stats.rtts_ms(q, 99) == (stats.rtt_ms(q), stats.rtt_ms(99))


@given(
    st.lists(st.floats(0.0, 0.05), min_size=0, max_size=400),
    st.floats(0.0, 3.0),
    st.floats(0.1, 3.0),
)
def test_the_achieved_rate_counts_the_replies_of_the_window_as_a_scan_would(
    steps: list[float], after: float, window: float
) -> None:
    """Found by bisection in the arrival-ordered times (no scan per snapshot), the same
    replies as reading every time against ``now - t <= window``, edges included."""
    stats = UnitStats(requested_rate_hz=50)
    t = 10.0
    for step in steps:
        t += step
        stats.on_reply(t, None)
    now = t + after
    recent = [r for r in stats._reply_times if now - r <= window]
    if len(recent) < 2:
        expected = 0.0
    else:
        last = recent[-1] if now - recent[-1] <= window / 4 else now
        span = last - recent[0]
        expected = (len(recent) - 1) / span if span > 0 else 0.0
    assert stats.achieved_rate_hz(now, window) == expected


_UNITS = {"left": 1, "right": 3}
_KINDS = ["time", "reply", "short reply", "fail", "send now", "status", "ask"]


@given(
    st.lists(
        st.tuples(st.sampled_from(_KINDS), st.sampled_from(list(_UNITS)), st.integers(0, 600)),
        max_size=80,
    )
)
def test_each_units_earliest_deadline_is_kept_true_and_a_step_leaves_nothing_due(
    steps: list[tuple[str, str, int]],
) -> None:
    """The scheduler keeps each unit's earliest deadline (``due``) instead of computing
    four per unit per step: after any input it equals the deadlines computed afresh, and
    after a step at ``now`` nothing of any unit is due at ``now`` (no unit skipped)."""
    cfg = parse_config(TWO_UNITS, "t.yaml")
    sched = BusScheduler(cfg.units.values(), now=0.0)
    now = 0.0
    for kind, unit, n in steps:
        abh3 = _UNITS[unit]
        if kind == "time":
            now += n / 1000
            sched.poll(now)
            assert all(slot.earliest_due() > now for slot in sched.slots.values())
        elif kind in ("reply", "short reply"):
            stats = sched.slots[unit].stats
            heard = stats.replies + stats.unsolicited + stats.malformed
            sched.on_frame(ids.dp0_reply_id(abh3, 2), bytes(8 if kind == "reply" else 3), now)
            assert stats.replies + stats.unsolicited + stats.malformed == heard + 1  # routed
        elif kind == "fail":
            sched.on_send_failed(sched.slots[unit].command_id)
        elif kind == "send now":
            sched.send_now(unit, now)
        elif kind == "status":
            sched.on_frame(ids.broadcast_id(abh3, 0, n % 7), bytes(8), now)
        else:
            sched.request_status(unit, n % 7)
        for slot in sched.slots.values():
            assert slot.due == slot.earliest_due()
        assert sched.next_deadline() == min(s.earliest_due() for s in sched.slots.values())


def test_turns_fill_up_to_the_bus_setting_and_never_split_a_robot() -> None:
    assert turns([("a", 1), ("b", 1), ("c", 1)], 4) == {"a": 0, "b": 0, "c": 0}
    assert turns([("a", 1), ("b", 1), ("c", 1)], 1) == {"a": 0, "b": 1, "c": 2}
    # a robot of 3 fills the first turn with one more; the next single starts turn 1
    assert turns([("rover", 3), ("a", 1), ("b", 1)], 4) == {"rover": 0, "a": 0, "b": 1}
    # a robot larger than a turn has one of its own, whole
    assert turns([("a", 1), ("big", 6), ("b", 1)], 4) == {"a": 0, "big": 1, "b": 2}
    assert turns([], 4) == {}


def _first_commands(text: str) -> dict[str, float]:
    """When each unit's first DP0 command goes, stepping the scheduler on a fine grid."""
    cfg = parse_config(text, "c.yaml")
    sched = BusScheduler(cfg.units.values(), now=0.0, units_per_turn=cfg.buses["b"].units_per_turn)
    names = {ids.dp0_command_id(u.abh3_id, u.host_id): n for n, u in cfg.units.items()}
    first: dict[str, float] = {}
    for step in range(200):  # 20 ms at 0.1 ms
        now = step / 10_000
        for ident, _ in sched.poll(now):
            if ident in names:
                first.setdefault(names[ident], now)
    return first


def test_six_units_go_in_two_turns_half_a_period_apart() -> None:
    units = "".join(f"  - {{name: u{i}, abh3_id: {i + 1}, host_id: 100}}\n" for i in range(6))
    first = _first_commands(f"buses: {{b: {{}}}}\nunits:\n{units}")
    period = 1 / 50  # the default command rate
    assert [first[f"u{i}"] for i in range(4)] == [0.0] * 4
    assert [first[f"u{i}"] for i in (4, 5)] == [pytest.approx(period / 2)] * 2
    alone = _first_commands(f"buses: {{b: {{units_per_turn: 1}}}}\nunits:\n{units}")
    # each on its own phase (stepped at 0.1 ms: a send on the first step at or after it)
    assert sorted(alone.values()) == pytest.approx([i * period / 6 for i in range(6)], abs=1e-4)


def test_turns_at_different_rates_never_land_on_one_another() -> None:
    """4 units at 100 Hz, 4 more, 4 at 50 and 4 at 25 Hz: four turns on the 100 Hz grid;
    no step sends more than one turn's commands (SocketCAN's default queue is 10)."""
    rates = [100] * 8 + [50] * 4 + [25] * 4
    units = "".join(
        f"  - {{name: u{i}, abh3_id: {i + 1}, host_id: 100, command_rate_hz: {r}}}\n"
        for i, r in enumerate(rates)
    )
    cfg = parse_config(f"buses: {{b: {{bitrate: 1000000}}}}\nunits:\n{units}", "c.yaml")
    sched = BusScheduler(cfg.units.values(), now=0.0)
    commands = {ids.dp0_command_id(u.abh3_id, u.host_id) for u in cfg.units.values()}
    most, sent = 0, 0
    for step in range(10_000):  # 1 s at 0.1 ms
        now = step / 10_000
        for unit in cfg.units.values():  # the drives answer within the step
            sched.on_frame(ids.dp0_reply_id(unit.abh3_id, unit.host_id), bytes(8), now)
        out = [i for i, _ in sched.poll(now) if i in commands]
        most, sent = max(most, len(out)), sent + len(out)
    assert most == 4
    assert sent == pytest.approx(8 * 100 + 4 * 50 + 4 * 25, abs=16)


def test_a_turns_replies_are_to_be_read_by_the_next_turn_on_the_grid() -> None:
    """``read_by`` (the pump's Turns): the next command or poll on the grid, though the
    exchanges in flight make the deadline wait for their replies; ``now`` while an
    online unit's reply is late past its turn (its command waits for it) or a parameter
    session is on; a late status reply or a unit not heard is never urgent."""
    text = (
        "buses: {b: {}}\nunits:\n"
        "  - {name: u, command_rate_hz: 100, broadcast: {mask: 0x01, rate_hz: 10}}\n"
    )
    reply = ids.dp0_reply_id(1, 2)
    sched = BusScheduler(parse_config(text, "c.yaml").units.values(), now=0.0)
    assert len(sched.poll(0.0)) == 1  # the command
    sched.on_frame(reply, bytes(8), 0.0008)  # heard: online
    assert sched.read_by(0.0008) == pytest.approx(0.005)  # the poll, half a period on
    assert len(sched.poll(0.005)) == 1  # the poll (its reply never comes)
    assert len(sched.poll(0.010)) == 1  # the next command; its reply not read yet
    assert sched.next_deadline() > 0.05  # the command after it waits for that reply...
    assert sched.read_by(0.010) == pytest.approx(0.020)  # ...which is read by its turn
    assert sched.read_by(0.0201) == 0.0201  # not read by then: late, read as it comes
    sched.on_frame(reply, bytes(8), 0.0202)
    assert len(sched.poll(0.0202)) == 1  # the next command, late by the reply
    assert sched.read_by(0.0202) == pytest.approx(0.030)
    slot = sched.slots["u"]
    slot.next_poll = 0.0201  # the poll's turn passed, its request unanswered: not urgent
    assert sched.read_by(0.0202) == pytest.approx(0.030)
    sched.params["u"].on_work()  # a parameter session queued: answers as they come
    assert sched.read_by(0.0202) == 0.0202

    silent = BusScheduler(parse_config(text, "c.yaml").units.values(), now=0.0)
    silent.poll(0.0)
    silent.poll(0.005)
    assert silent.poll(0.010) == []  # never heard: the command waits for its timeout
    assert silent.read_by(0.0101) == pytest.approx(0.105)  # not urgent: the next poll


def test_a_robots_frames_sent_at_once_one_after_the_other_keep_one_turn() -> None:
    """The robot's drives sent out of schedule a few microseconds apart (its readiness, an
    e-stop): the later one joins the earlier one's next grid point, so the robot's frames
    leave in one turn again rather than parted by those microseconds for good."""
    cfg = parse_config(TWO_UNITS, "t.yaml")
    units = list(cfg.units.values())
    scheduler = BusScheduler(units, 0.0, together={"left": "r", "right": "r"})
    scheduler.send_now("left", 1.000)
    scheduler.send_now("right", 1.00004)
    left, right = scheduler.slots["left"], scheduler.slots["right"]
    assert right.next_command == left.next_command == pytest.approx(1.02)
    alone = BusScheduler(units, 0.0)  # not one robot: each keeps its own
    alone.send_now("left", 1.000)
    alone.send_now("right", 1.00004)
    assert alone.slots["right"].next_command == pytest.approx(1.02004)
