"""Finding the TelABH3 string form a drive reads (issue 22 item 7): a unit without a
``telabh3:`` setting tries each form with its first exchange, keeps the one the drive
answers and says which; a drive that reads none is reported so, not as a timeout. On the
fake clock against simulated drives that read only one form (``simulate.telabh3_form``),
every frame checked against the J1939 rules."""

from __future__ import annotations

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.params.session import PROBE_REPLY_WAIT, FormFound, Result
from abh3_supervisor.params.telabh3 import FORMS, Checksum, Command, Request, TelFormat, pin
from tests.support.j1939 import check_j1939
from tests.support.rig import Rig

UNITS = """
buses:
  b: {{interface: virtual, channel: t, simulate: {simulate}}}
units:
  - {{name: left, abh3_id: 1{left}}}
  - {{name: right, abh3_id: 3, protocol: "2023"}}
"""
YAML_FORM = {
    FORMS[0]: "{header: false, checksum: with_header}",
    FORMS[1]: "{header: true}",
    FORMS[2]: "{header: false, checksum: as_sent}",
}


def rig_reading(form: str, left: str = "") -> Rig:
    """Left's simulated drive reads only ``form`` (a YAML value of telabh3_form)."""
    return Rig(
        parse_config(UNITS.format(simulate=f"{{telabh3_form: {{left: {form}}}}}", left=left))
    )


def submit(rig: Rig, *requests: Request) -> list[Result]:
    results: list[Result] = []
    for r in requests:
        rig.scheduler.params["left"].submit(r, results.append)
    return results


def only_requests(messages: list[bytes]) -> list[bytes]:
    """The host's strings among every transport message (replies carry ACK or NAK)."""
    return [m for m in messages if b"\x06" not in m and b"\x15" not in m]


def found(rig: Rig) -> list[FormFound]:
    seen: list[FormFound] = []
    rig.scheduler.params["left"].on_form = seen.append
    return seen


@pytest.mark.parametrize("form", FORMS, ids=lambda f: pin(f))
def test_the_form_a_drive_reads_is_found_without_a_setting(form: TelFormat) -> None:
    rig = rig_reading(YAML_FORM[form])
    told = found(rig)
    results = submit(rig, Request(Command.PARAM, 0x4117), Request(Command.PARAM, 0x5000))
    rig.run(3.0)
    assert [r.ok for r in results] == [True, True]
    assert results[0].reply is not None and results[0].reply.word == 0x00400005  # 500 ms
    channel = rig.scheduler.params["left"]
    assert channel.fmt == form and not channel.pinned
    assert [f.fmt for f in told] == [form]  # said once: the second request just uses it
    assert pin(form) in told[0].text()
    before = FORMS.index(form)
    assert len(told[0].tried) == before  # each form before it: "CP4117.. no reply …"
    assert all(f"no reply within {PROBE_REPLY_WAIT:g} s" in t for t in told[0].tried)
    messages = check_j1939(rig.timeline.frames)
    requests = only_requests(messages)
    assert requests[before].startswith(Request(Command.PARAM, 0x4117).text(form).encode())
    assert requests[-1].startswith(Request(Command.PARAM, 0x5000).text(form).encode())
    assert results[0].fmt == form


def test_the_right_drive_is_untouched_by_the_left_ones_limit() -> None:
    rig = rig_reading("none")
    results: list[Result] = []
    rig.scheduler.params["right"].submit(Request(Command.PARAM, 0x4117), results.append)
    rig.run(0.5)
    assert results[0].ok and rig.scheduler.params["right"].fmt == FORMS[0]


def test_a_drive_that_reads_no_form_is_said_so_not_timed_out() -> None:
    rig = rig_reading("none")
    told = found(rig)
    results = submit(rig, Request(Command.PARAM, 0x4117))
    rig.run(4.0)
    error = results[0].error
    assert error is not None and error.startswith("the drive answers none of the TelABH3 forms: ")
    for form in FORMS:
        assert f"{Request(Command.PARAM, 0x4117).text(form)} no reply" in error
    assert "set telabh3: in the unit" in error
    assert "1.25 s" not in error  # not the transport's timeout
    assert [f.fmt for f in told] == [None]
    assert rig.scheduler.params["left"].fmt is None  # the next request tries again
    # three forms: each no more than the probe's wait, the guard between: about 2 s
    assert results[0].t < 3 * PROBE_REPLY_WAIT + 2 * 0.25 + 0.1
    check_j1939(rig.timeline.frames)


def test_a_write_first_is_preceded_by_a_harmless_identity_read() -> None:
    rig = rig_reading("{header: true}")
    results = submit(rig, Request(Command.PARAM, 0x5000, 0x00400009))  # 900
    rig.run(3.0)
    assert results[0].ok
    assert rig.drive("left").tel.params[0x5000] == 0x00400009
    requests = only_requests(check_j1939(rig.timeline.frames))
    # BI 2 in the default form (unread), then in the serial form, then the write in it
    assert requests[0].startswith(b"BI00029B")
    assert requests[1].startswith(b"FFFFBI00029B")
    assert requests[2].startswith(b"FFFFCP500000400009")
    assert len(requests) == 3  # the write went once, in the form found


def test_a_refused_read_first_does_not_pin_a_wrong_form() -> None:
    """A NAK may be the address's, not the form's: the identity settles it."""
    rig = rig_reading("{header: false, checksum: as_sent}")
    told = found(rig)
    results = submit(rig, Request(Command.PARAM, 0x1234))  # no such parameter: NAK
    rig.run(3.0)
    assert results[0].error is None and results[0].reply is not None
    assert not results[0].reply.ok  # the caller gets the drive's NAK to its address
    assert rig.scheduler.params["left"].fmt == FORMS[2]
    assert told[0].fmt == FORMS[2]


def test_a_pinned_form_is_never_probed() -> None:
    rig = rig_reading("{header: true}", left=", telabh3: {header: false}")
    results = submit(rig, Request(Command.PARAM, 0x4117))
    rig.run(3.0)
    assert results[0].error == "no reply from the drive within 1.25 s"  # as it was
    assert rig.scheduler.params["left"].pinned


def test_a_transport_failure_is_not_taken_for_a_form_problem() -> None:
    rig = rig_reading("any")
    told = found(rig)
    rig.drive("left").faults = (Fault(FaultKind.TP_LOST_CTS, 0.0, 100.0),)
    results = submit(rig, Request(Command.PARAM, 0x4117))
    rig.run(3.0)
    assert results[0].error == "no CTS from the drive within 1.25 s"
    assert told == [] and rig.scheduler.params["left"].fmt is None


def test_a_caller_giving_up_mid_probe_ends_it() -> None:
    rig = rig_reading("{header: true}")
    results = submit(rig, Request(Command.PARAM, 0x4117))
    rig.run(0.3)  # the default form is unanswered, the probe still waits
    channel = rig.scheduler.params["left"]
    channel.withdraw(results.append, "no answer")
    rig.run(3.0)
    assert [r.error for r in results] == ["no answer"]
    assert not channel.busy and channel.fmt is None


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("{left: sometimes}", "telabh3_form.left: expected {header: …, checksum: …}"),
        ("{middle: none}", "telabh3_form.middle: no unit 'middle' on bus b"),
        ("{left: {header: maybe}}", "telabh3_form.left.header: expected true or false"),
        ("{left: {hedaer: true}}", "did you mean 'header'"),
    ],
)
def test_telabh3_form_mistakes_are_file_line_errors(value: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(UNITS.format(simulate=f"{{telabh3_form: {value}}}", left=""), "f.yaml")
    assert any(p.startswith("f.yaml:3: ") and message in p for p in info.value.problems), (
        info.value.problems
    )


def test_the_simulator_reads_the_forms_it_is_given() -> None:
    config = parse_config(
        UNITS.format(simulate="{telabh3_form: {left: {header: true, checksum: as_sent}}}", left="")
    )
    sim = config.buses["b"].simulate
    assert sim is not None
    assert sim.forms_of("left") == (TelFormat(True, Checksum.AS_SENT),)  # = the serial form
    assert sim.forms_of("right") is None
    assert config.units["left"].telabh3 is None  # no setting: found at first use


def test_a_write_whose_probe_fails_on_the_transport_is_told_its_own_request() -> None:
    rig = rig_reading("any")
    rig.drive("left").faults = (Fault(FaultKind.TP_ABORT, 0.0, 100.0),)
    write = Request(Command.PARAM, 0x5000, 0x00400009)
    results = submit(rig, write)
    rig.run(1.0)
    assert [(r.request, r.error) for r in results] == [
        (write, "the drive aborted the transfer: resources")
    ]
    assert rig.drive("left").tel.params[0x5000] != 0x00400009  # nothing written
