"""The J1939 transport on the fake-clock bus: sessions both ways against the simulated
drive, faults, and an independent check of every recorded frame against the J1939 rules."""

from __future__ import annotations

import itertools
from collections import defaultdict

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.params.session import ABORT_GUARD, Result
from abh3_supervisor.params.telabh3 import Command, Request, decode_reply
from abh3_supervisor.params.transport import Receiver, Sender, State
from tests.support.j1939 import check_j1939, dp0_sends
from tests.support.rig import TWO_UNITS, Rig


def submit(rig: Rig, unit: str, *requests: Request) -> list[Result]:
    results: list[Result] = []
    for r in requests:
        rig.scheduler.params[unit].submit(r, results.append)
    return results


def test_read_write_read_against_the_simulated_drive(rig: Rig) -> None:
    speed = 0x5000
    results = submit(
        rig,
        "left",
        Request(Command.PARAM, speed),
        Request(Command.PARAM, speed, 0x00600005),  # 5 × 10³ = 5000
        Request(Command.PARAM, speed),
        Request(Command.IDENTITY, 2),
        Request(Command.PARAM, 0x1234),
    )
    rig.run(0.5)
    assert [r.error for r in results] == [None] * 5
    assert results[0].reply is not None and results[0].reply.word == 0x00400008  # 800
    assert results[2].reply is not None and results[2].reply.word == 0x00600005
    assert rig.drive("left").tel.params[speed] == 0x00600005
    assert results[3].reply is not None and results[3].reply.data == "2.3.0.1"
    assert results[4].reply is not None and not results[4].reply.ok  # NAK: unknown
    messages = check_j1939([f for f in rig.timeline.frames])
    assert len(messages) == 10  # a request and a reply each
    assert messages[0] == b"CP500090\x16"  # default form: no header, checksum as with FFFF
    assert decode_reply(messages[1]).word == 0x00400008


def test_the_serial_form_is_a_per_unit_setting() -> None:
    text = TWO_UNITS.replace(
        "broadcast: {mask: 0x7f, rate_hz: 14}}",
        "broadcast: {mask: 0x7f, rate_hz: 14}, telabh3: {header: true}}",
    )
    rig = Rig(parse_config(text, "two.yaml"))
    results = submit(rig, "left", Request(Command.MONITOR, 0x1012))
    rig.run(0.2)
    assert results[0].ok
    assert check_j1939(rig.timeline.frames)[0].startswith(b"FFFFCM101294")


def test_monitors_follow_the_simulated_drive(rig: Rig) -> None:
    rig.sup.apply_text("left", "SERVO ON ON")
    rig.sup.apply_text("left", "START ON ON")
    rig.sup.apply_text("left", "VEL 120 0")
    rig.run(1.0)
    results = submit(
        rig, "left", Request(Command.MONITOR, 0x1012), Request(Command.MONITOR, 0x1054)
    )
    rig.run(0.1)
    from abh3_supervisor.params.telabh3 import unpack_float

    assert results[0].reply is not None
    assert unpack_float(results[0].reply.word) == pytest.approx(120, abs=0.5)
    assert results[1].reply is not None and results[1].reply.word > 0  # pulses counted


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        (FaultKind.TP_LOST_CTS, "no CTS from the drive within 1.25 s"),
        (FaultKind.TP_ABORT, "the drive aborted the transfer: resources"),
        (FaultKind.TP_SLOW_DT, "the drive stopped sending: DT 2 of 2 did not come within 1.25 s"),
    ],
)
def test_transport_faults_end_with_a_clear_error_and_no_hang(kind: FaultKind, message: str) -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    fault = Fault(kind, 0.0, 100.0, delay_ms=2000.0)
    rig.drive("left").faults = (fault,)
    results = submit(rig, "left", Request(Command.PARAM, 0x4117))
    rig.run(5.0)
    assert [r.error for r in results] == [message]
    rig.drive("left").faults = ()
    after = submit(rig, "left", Request(Command.PARAM, 0x4117))  # the channel is free again
    rig.run(5.0)
    assert after[0].ok
    aborts = [
        f
        for f in rig.timeline.frames
        if f.arbitration_id >> 16 & 0xFF == 0xEC and f.data[0] == 0xFF
    ]
    if kind is not FaultKind.TP_ABORT:  # we abort (reason 3, timeout) what we gave up on
        assert [(f.node, f.data[1]) for f in aborts] == [(0, 3)]


def test_slow_drive_dts_within_the_timeout_still_arrive() -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.drive("left").faults = (Fault(FaultKind.TP_SLOW_DT, 0.0, 100.0, delay_ms=300.0),)
    results = submit(rig, "left", Request(Command.IDENTITY, 2))
    rig.run(3.0)
    assert results[0].reply is not None and results[0].reply.data == "2.3.0.1"
    dts = [
        f.start
        for f in rig.timeline.frames
        if f.arbitration_id >> 16 & 0xFF == 0xEB and f.node == 1
    ]
    assert dts[1] - dts[0] == pytest.approx(0.3, abs=0.001)


def test_a_second_rts_while_a_session_is_open_is_aborted_busy() -> None:
    receiver = Receiver(0x00EC0201, 0x00EB0201)
    assert receiver.on_rts(bytes([0x10, 20, 0, 3, 0xFF, 0, 0xEF, 0]), 0.0)
    assert receiver.poll(0.0) == [(0x00EC0201, bytes([0x11, 3, 1, 0xFF, 0xFF, 0, 0xEF, 0]))]
    assert not receiver.on_rts(bytes([0x10, 20, 0, 3, 0xFF, 0, 0xEF, 0]), 0.001)
    receiver.on_dt(bytes([2]) + bytes(7), 0.002)  # out of sequence
    assert receiver.state is State.FAILED
    assert receiver.poll(0.003) == [(0x00EC0201, bytes([0xFF, 7, 0xFF, 0xFF, 0xFF, 0, 0xEF, 0]))]


def test_receiver_asks_for_sixteen_dts_per_cts() -> None:
    message = bytes(range(200))  # 29 DTs
    sender = Sender(message, 0x00EC0102, 0x00EB0102, 0.0)
    receiver = Receiver(0x00EC0201, 0x00EB0201)
    wire: dict[str, list[bytes]] = defaultdict(list)
    now = 0.0
    for _ in range(100):
        for ident, data in sender.poll(now):
            wire["s"].append(data)
            if ident >> 16 & 0xFF == 0xEC:
                receiver.on_rts(data, now)
            else:
                receiver.on_dt(data, now)
        for _, data in receiver.poll(now):
            wire["r"].append(data)
            sender.on_cm(data, now)
        now += 0.001
    assert sender.state is State.DONE and receiver.message == message
    assert [d[1:3] for d in wire["r"] if d[0] == 0x11] == [bytes([16, 1]), bytes([13, 17])]


def test_a_dump_leaves_every_units_dp0_rate_within_one_percent() -> None:
    from abh3_supervisor.params import table
    from abh3_supervisor.params.telabh3 import pack_float

    rig = Rig(parse_config(TWO_UNITS, "two.yaml"), bitrate=500_000)  # wire time modelled
    rig.drive("left").tel.params[0x4119] = pack_float(30)  # the drive waits 30 ms between DTs
    rig.run(1.0)
    start = rig.timeline.now
    results = submit(rig, "left", *(Request(Command.PARAM, e.address) for e in table.PARAMETERS))
    while len(results) < len(table.PARAMETERS):
        rig.run(0.05)
    end = max(r.t for r in results)
    assert all(r.ok for r in results) and end - start > 3.0  # 121 parameters, ~4 s
    for abh3 in (3, 1):  # the other unit, and the one being dumped
        sent = dp0_sends(rig.timeline.frames, abh3, start, end)
        rate = (len(sent) - 1) / (sent[-1] - sent[0])
        assert rate == pytest.approx(50, rel=0.01)
        assert max(b - a for a, b in itertools.pairwise(sent)) < 0.021  # never a late keepalive
    assert rig.scheduler.slots["right"].stats.timeouts == 0
    assert len(check_j1939(rig.timeline.frames)) == 2 * len(table.PARAMETERS)


def test_a_refused_transport_frame_fails_the_request_at_once_and_frees_the_channel(
    rig: Rig,
) -> None:
    """Free again after the guard that follows any failed exchange (test_j1939_abort.py)."""
    rig.run(0.1)
    rig.timeline.refuse_sends(0, 0.1, 0.2)
    results = submit(rig, "left", Request(Command.PARAM, 0x5000))
    rig.run(0.05)
    assert [r.error for r in results] == ["the bus refused a transport frame (is the bus up?)"]
    assert results[0].t == pytest.approx(0.1, abs=0.002)
    rig.run(0.1)
    again = submit(rig, "left", Request(Command.PARAM, 0x5000))
    rig.run(ABORT_GUARD)
    assert again[0].ok


def test_cancel_ends_the_open_exchange_and_the_queue(rig: Rig) -> None:
    results = submit(rig, "left", Request(Command.PARAM, 0x5000), Request(Command.PARAM, 0x5001))
    rig.drive("left").faults = (Fault(FaultKind.TP_LOST_CTS, 0.0, 100.0),)
    rig.run(0.01)
    rig.scheduler.params["left"].cancel("the run ends")
    rig.run(0.01)
    assert sorted(r.error or "" for r in results) == ["the run ends", "the run ends"]
    assert not rig.scheduler.params["left"].busy


def test_a_caller_that_stops_waiting_takes_back_only_its_own_request(rig: Rig) -> None:
    """One client's deadline passing (``ParamOps``) must not fail another's requests."""
    channel = rig.scheduler.params["left"]
    rig.drive("left").faults = (Fault(FaultKind.TP_LOST_CTS, 0.0, 0.05),)  # the first: unheard
    opened: list[Result] = []
    theirs: list[Result] = []
    queued: list[Result] = []
    channel.submit(Request(Command.PARAM, 0x5000), opened.append)
    channel.submit(Request(Command.PARAM, 0x5001), theirs.append)
    channel.submit(Request(Command.PARAM, 0x5002), queued.append)
    channel.withdraw(queued.append, "no answer")  # still queued: dropped, nothing to say
    assert len(channel.queue) == 2
    rig.run(0.1)  # the first is open, waiting for a CTS that does not come
    assert channel.current is not None and not opened
    channel.withdraw(opened.append, "no answer")  # our abort closes the drive's side too
    rig.run(0.5)
    assert [r.error for r in opened] == ["no answer"] and queued == []
    assert len(theirs) == 1 and theirs[0].ok
