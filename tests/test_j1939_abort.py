"""A CTS that answers an RTS we have given up on must never clear the next request's DTs
(issue 22 item 8), on the fake-clock bus with wire time modelled.

J1939-21: a CTS answers the most recent RTS of its connection. After we abort (or give
up), a CTS the drive put on the wire before it heard our abort can still reach us; taken
by the next request's sender, it would send DTs the drive never asked for. The rule
(params/session.py, transport.py): after a failed exchange the channel waits
``ABORT_GUARD`` before the next RTS, dropping the drive's transport frames meanwhile; and
the first CTS of a session must ask for packet 1."""

from __future__ import annotations

import math
from collections.abc import Callable

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.params.session import ABORT_GUARD, Result
from abh3_supervisor.params.telabh3 import Command, Request, pack_float
from abh3_supervisor.params.transport import Sender, State, cts
from abh3_supervisor.simulator.timeline import WireFrame
from tests.support.j1939 import check_j1939
from tests.support.rig import TWO_UNITS, Rig

HOST, LEFT = 0, 1  # timeline nodes: the scheduler, the simulated drives
HOST_CM, HOST_DT, DRIVE_CM = 0x00EC0102, 0x00EB0102, 0x00EC0201  # host 2, left 1


def is_host_abort(f: WireFrame) -> bool:
    return f.node == HOST and f.arbitration_id == HOST_CM and f.data[0] == 0xFF


class LateFrames:
    """A node that puts ``frames`` on the bus ``delay`` s after it first sees a frame for
    which ``trigger`` holds: a frame the drive sent before it heard our abort, delivered
    late (an adapter's queue, the kernel, a drive answering out of J1939's time)."""

    def __init__(
        self, trigger: Callable[[int, bytes], bool], frames: list[tuple[int, bytes]], delay: float
    ) -> None:
        self.trigger, self.frames, self.delay = trigger, frames, delay
        self.due = math.inf
        self.fired = False

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        if not self.fired and self.trigger(arbitration_id, data):
            self.fired, self.due = True, now + self.delay

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        if now < self.due:
            return []
        self.due = math.inf
        return self.frames

    def next_deadline(self) -> float:
        return self.due

    def on_send_failed(self, arbitration_id: int) -> None:
        pass

    def on_bad_frame(self, arbitration_id: int, now: float, reason: str) -> None:
        pass


def assert_next_dts_wait_for_a_fresh_cts(frames: list[WireFrame], drive: int = LEFT) -> None:
    """After our abort, no DT of ours goes before the drive's CTS to the RTS that follows
    the abort: each DT window is opened by a CTS sent after our newest RTS."""
    abort = next(i for i, f in enumerate(frames) if is_host_abort(f))
    rts: WireFrame | None = None
    open_window = False
    for f in frames[abort + 1 :]:
        if f.node == HOST and f.arbitration_id == HOST_CM and f.data[0] == 0x10:
            rts, open_window = f, False
        elif f.node == drive and f.arbitration_id == DRIVE_CM and f.data[0] == 0x11:
            open_window = rts is not None and f.start >= rts.end
        elif f.node == HOST and f.arbitration_id == HOST_DT:
            assert rts is not None, f"DT {f} before any RTS after the abort"
            assert open_window, f"DT {f} without a CTS that answers the RTS at {rts.start}"
    assert rts is not None, "the next request never started"


def test_a_cts_on_the_wire_when_we_give_up_does_not_clear_the_next_requests_dts() -> None:
    """The caller gives up right after our RTS; the drive's CTS to it is already on the
    wire (it arrives after the abort is decided). The next request waits for its own.
    The units on phases of their own: the moment to give up was found on that wire."""
    apart = TWO_UNITS.replace("simulate: true}", "simulate: true, units_per_turn: 1}")
    rig = Rig(parse_config(apart, "two.yaml"), bitrate=500_000)
    channel = rig.scheduler.params["left"]
    rig.run(0.1)
    given_up: list[Result] = []
    after: list[Result] = []
    channel.submit(Request(Command.PARAM, 0x5000), given_up.append)
    channel.submit(Request(Command.PARAM, 0x5001), after.append)
    start = len(rig.timeline.frames)
    for _ in range(1000):  # until our RTS has gone out (the drive answers it at once)
        rig.run(0.00002)
        if any(f.arbitration_id == HOST_CM for f in rig.timeline.frames[start:]):
            break
    assert not any(f.arbitration_id == DRIVE_CM for f in rig.timeline.frames[start:])
    channel.withdraw(given_up.append, "the caller gave up")
    rig.run(1.0)
    assert [r.error for r in given_up] == ["the caller gave up"]
    assert len(after) == 1 and after[0].ok, after
    assert after[0].reply is not None and after[0].reply.word == pack_float(400)  # SPEED_AY_1
    frames = rig.timeline.frames[start:]
    drive_cts = [f for f in frames if f.arbitration_id == DRIVE_CM and f.data[0] == 0x11]
    abort = next(f for f in frames if is_host_abort(f))
    # the drive's first CTS answers the RTS we gave up on: queued before the drive heard
    # our abort, it lost arbitration to it and reached us after the abort was decided
    assert drive_cts[0].start <= abort.end
    assert_next_dts_wait_for_a_fresh_cts(frames)
    check_j1939([f for f in frames if f is not drive_cts[0]])  # it crossed our abort


def test_a_late_cts_after_our_timeout_abort_is_dropped() -> None:
    """The drive misses our RTS, we time out and abort; a CTS to that RTS comes 5 ms
    after the abort. The next request's RTS waits out the guard and gets its own CTS."""
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"), bitrate=500_000)
    rig.drive("left").faults = (Fault(FaultKind.TP_LOST_CTS, 0.0, 1.45),)
    late = LateFrames(
        lambda ident, data: ident == HOST_CM and data[0] == 0xFF,
        [(DRIVE_CM, cts(2, 1))],  # "send 2 packets from 1": fits the next request exactly
        0.005,
    )
    injector = rig.timeline.add(late)
    rig.run(0.1)
    timed_out: list[Result] = []
    after: list[Result] = []
    channel = rig.scheduler.params["left"]
    channel.submit(Request(Command.PARAM, 0x5000), timed_out.append)
    channel.submit(Request(Command.PARAM, 0x5001), after.append)
    rig.run(3.0)
    assert [r.error for r in timed_out] == ["no CTS from the drive within 1.25 s"]
    assert len(after) == 1 and after[0].ok, after
    assert after[0].reply is not None and after[0].reply.word == pack_float(400)
    frames = rig.timeline.frames
    abort = next(f for f in frames if is_host_abort(f))
    stale = next(f for f in frames if f.node == injector)
    assert stale.start - abort.end < ABORT_GUARD  # it came while the guard held
    next_rts = next(
        f
        for f in frames
        if f.node == HOST
        and f.arbitration_id == HOST_CM
        and f.data[0] == 0x10
        and f.start > stale.start
    )
    assert next_rts.start >= abort.start + ABORT_GUARD
    assert_next_dts_wait_for_a_fresh_cts(frames)
    check_j1939([f for f in frames if f.node != injector])


def test_a_success_is_not_followed_by_a_guard(rig: Rig) -> None:
    results: list[Result] = []
    for address in (0x5000, 0x5001):
        rig.scheduler.params["left"].submit(Request(Command.PARAM, address), results.append)
    rig.run(0.1)
    assert [r.ok for r in results] == [True, True]
    assert results[1].t - results[0].t < 0.01


def test_the_guard_also_holds_a_request_submitted_later(rig: Rig) -> None:
    channel = rig.scheduler.params["left"]
    rig.run(0.1)
    rig.timeline.refuse_sends(HOST, 0.1, 0.15)
    failed: list[Result] = []
    channel.submit(Request(Command.PARAM, 0x5000), failed.append)
    rig.run(0.1)
    assert [r.error for r in failed] == ["the bus refused a transport frame (is the bus up?)"]
    later: list[Result] = []
    channel.submit(Request(Command.PARAM, 0x5000), later.append)
    rig.run(ABORT_GUARD)
    assert later and later[0].ok and later[0].t >= failed[0].t + ABORT_GUARD


# ------------------------------------------------------------ the sender alone


def sender_with_rts() -> tuple[Sender, list[tuple[int, bytes]]]:
    sender = Sender(b"CP500090\x16", HOST_CM, HOST_DT, 0.0)
    return sender, sender.poll(0.0)


def test_a_first_cts_that_does_not_ask_for_packet_one_answers_another_rts() -> None:
    sender, out = sender_with_rts()
    assert [d[0] for _, d in out] == [0x10]
    sender.on_cm(cts(1, 2), 0.001)  # "packet 2 next": the rest of an older session
    assert sender.state is State.WAIT and sender.poll(0.001) == []  # ignored: no DT, no abort
    sender.on_cm(cts(2, 1), 0.002)  # ours
    assert [d[0] for _, d in sender.poll(0.002)] == [1, 2]
    assert not sender.finished


def test_a_hold_then_the_real_cts_still_works() -> None:
    sender, _ = sender_with_rts()
    sender.on_cm(cts(0, 0xFF), 0.5)  # hold: the deadline moves on
    assert sender.poll(1.6) == [] and sender.state is State.WAIT
    sender.on_cm(cts(2, 1), 1.7)
    assert [d[0] for _, d in sender.poll(1.7)] == [1, 2]


def test_a_cts_before_our_rts_went_out_is_not_an_answer() -> None:
    sender = Sender(b"CP500090\x16", HOST_CM, HOST_DT, 0.0)
    sender.on_cm(cts(2, 1), 0.0)  # still START: the RTS has not been sent
    assert [d[0] for _, d in sender.poll(0.0)] == [0x10]
    assert sender.state is State.WAIT
