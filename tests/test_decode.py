"""`abh3 decode` reads past what it cannot read, says where, and never shows a traceback."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.decode import SHOWN, decode_file, read_messages
from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.protocol import ids
from tests.support.rig import TWO_UNITS, Rig, present, set_velocity

FORMATS = (".log", ".asc", ".blf", ".csv")
# DP0 command and reply of drive 1 (host 2), as `abh3 run --record` writes them
GOOD_LOG = (
    "(1.000000) can0 00EF0102#F401000001100000 T\n(1.001000) can0 00EF0201#F3FF0000FAFF0D00 R\n"
)


def frames(count: int) -> Iterator[can.Message]:
    for i in range(count):
        reply = i % 2 == 1
        yield can.Message(
            timestamp=1000.0 + i / 100,
            arbitration_id=ids.dp0_reply_id(1, 2) if reply else ids.dp0_command_id(1, 2),
            data=bytes([i % 256, 1, 0, 0, 0x11, 0, 0, i % 7]),
            is_extended_id=True,
            is_rx=reply,
            channel="can0",
        )


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """40 frames in each format, written by python-can's writers as --record does."""
    out = {}
    for suffix in FORMATS:
        path = tmp_path_factory.mktemp("rec") / f"rec{suffix}"
        writer = can.Logger(str(path))
        for msg in frames(40):
            writer.on_message_received(msg)
        writer.stop()
        out[suffix] = path.read_bytes()
    return out


def decode(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str], list[str]]:
    code = main(["decode", str(path)])
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    return code, out.out.splitlines(), out.err.splitlines()


@pytest.mark.wallclock
def test_bad_lines_are_reported_by_number_and_the_rest_is_decoded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mixed = tmp_path / "mixed.log"
    mixed.write_text("garbage\n" + GOOD_LOG + "(1.002000) can0 00EF0102#zz T\n\n" + GOOD_LOG)
    code, out, err = decode(mixed, capsys)
    assert code == 0 and len(out) == 4 and all("dp0_" in line for line in out)
    # without --config the reply's shape tells its generation first (said once, not twice)
    guessed, *err = err
    assert guessed == "decode: address 1 looks like a 2023 drive (no --config): guessed"
    assert err[0].startswith(f"{mixed}:1: cannot read 'garbage'")
    assert err[1].startswith(f"{mixed}:4: cannot read '(1.002000) can0 00EF0102#zz T'")
    assert err[2] == f"{mixed}: 2 unreadable line(s) skipped, 4 frame(s) read"
    assert len(err) == 3  # the first pass that guessed reported nothing


@pytest.mark.wallclock
def test_an_asc_file_goes_on_with_its_header_settings_after_a_bad_frame(
    tmp_path: Path, recordings: dict[str, bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    lines = recordings[".asc"].decode().splitlines(keepends=True)
    first = next(i for i, line in enumerate(lines) if " Rx " in line or " Tx " in line)
    lines[first + 1] = lines[first + 1].replace(" d 8 ", " d 8 zz ")  # a byte that is not hex
    broken = tmp_path / "broken.asc"
    broken.write_text("".join(lines))
    code, out, err = decode(broken, capsys)
    assert code == 0 and len(out) == 39
    assert err.pop(0).endswith(": guessed")
    assert err[0].startswith(f"{broken}:{first + 2}: cannot read")
    assert err[-1] == f"{broken}: 1 unreadable line(s) skipped, 39 frame(s) read"


@pytest.mark.wallclock
def test_only_the_first_lines_are_shown_then_the_count(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    noisy = tmp_path / "noisy.csv"
    noisy.write_text(
        "timestamp,id,ext,rtr,err,dlc,data\n" + "x\n" * 30 + "1.0,18EF0102,1,0,0,1,AA==\n"
    )
    code, out, err = decode(noisy, capsys)
    assert code == 0 and len(out) == 1
    assert (
        len(err) == SHOWN + 1
        and err[-1] == f"{noisy}: 30 unreadable line(s) skipped, 1 frame(s) read"
    )


@pytest.mark.wallclock
@pytest.mark.parametrize("suffix", FORMATS)
def test_a_file_with_nothing_readable_is_an_error(
    suffix: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    junk = tmp_path / f"junk{suffix}"
    junk.write_bytes(b"\x7fELF\x02\x01\x01\x00 not a recording \xff\xfe\n" * 3)
    code, out, err = decode(junk, capsys)
    assert code == 2 and out == []
    assert err[-1] == f"error: {junk}: no frame could be read: is it a {suffix} recording?"


@pytest.mark.wallclock
def test_an_empty_recording_decodes_to_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    empty = tmp_path / "empty.log"
    empty.write_text("")
    assert decode(empty, capsys) == (0, [], [])


@pytest.mark.parametrize("suffix", FORMATS)
@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_a_recording_cut_anywhere_decodes_what_it_holds(
    suffix: str, data: st.DataObject, recordings: dict[str, bytes], tmp_path: Path
) -> None:
    whole = recordings[suffix]
    cut = data.draw(st.integers(0, len(whole)), label="cut")
    path = tmp_path / f"cut{suffix}"
    path.write_bytes(whole[:cut])
    reports: list[str] = []
    try:
        got = list(read_messages(path, reports.append))
        text = list(decode_file(path, None, as_json=True))
    except Abh3Error as exc:  # nothing left to read: said, not raised as a traceback
        assert "no frame could be read" in str(exc)
        return
    expected = list(frames(40))
    assert len(got) == len(text) <= len(expected)
    for msg, want in zip(got[:-1], expected, strict=False):  # the last may be cut short
        assert (msg.arbitration_id, bytes(msg.data)) == (want.arbitration_id, bytes(want.data))
    assert len(reports) <= SHOWN + 1


@pytest.mark.parametrize("suffix", FORMATS)
@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(junk=st.binary(max_size=600), at=st.integers(0, 4000))
def test_garbage_anywhere_never_raises_anything_but_a_clear_error(
    suffix: str, junk: bytes, at: int, recordings: dict[str, bytes], tmp_path: Path
) -> None:
    whole = recordings[suffix]
    path = tmp_path / f"mixed{suffix}"
    path.write_bytes(whole[:at] + junk + whole[at:])
    try:
        list(decode_file(path, None, as_json=False))
    except Abh3Error as exc:
        assert "no frame could be read" in str(exc)


@pytest.mark.wallclock
def test_frames_named_by_bus_as_in_an_mcap_recording_get_their_units_generation() -> None:
    """MCAP topics carry the bus's name, not its channel: a 2023 unit's reply read back
    from one is still named and decoded in 2023, beside a 2021 unit at the same address."""
    from abh3_supervisor.clients.decode import address_books, record, unit_names
    from abh3_supervisor.config import parse_config
    from abh3_supervisor.protocol import ids

    config = parse_config(
        "buses:\n  left: {interface: socketcan, channel: vcan0}\n"
        "  right: {interface: socketcan, channel: vcan1}\n"
        "units:\n  - {name: l, bus: left, abh3_id: 1}\n"
        "  - {name: r, bus: right, abh3_id: 1, protocol: '2023'}\n",
        "two.yaml",
    )
    books, names = address_books(config), unit_names(config)
    for channel in ("vcan1", "right"):  # a candump log, an MCAP recording
        msg = can.Message(arbitration_id=ids.dp0_reply_id(1, 2), data=bytes(8), channel=channel)
        decoded = record(msg, books, names)
        assert (decoded["unit"], decoded["protocol"]) == ("r", "2023"), channel


# ---------------------------------------------------------------- no --config: guessed


def record_traffic(rig: Rig, path: Path, channel: str = "can0") -> None:
    """What crossed the simulated wire, as ``--record`` writes it."""
    writer = can.Logger(str(path))
    for f in rig.timeline.frames:
        writer.on_message_received(
            can.Message(
                timestamp=f.start,
                arbitration_id=f.arbitration_id,
                data=f.data,
                is_extended_id=True,
                channel=channel,
            )
        )
    writer.stop()


def decoded(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[list[Any], list[str]]:
    assert main(["decode", *args, "--json"]) == 0
    out = capsys.readouterr()
    return [json.loads(line) for line in out.out.splitlines()], out.err.splitlines()


@pytest.mark.wallclock
def test_decode_without_config_guesses_each_addresses_generation_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))  # drive 1 speaks 2021, drive 3 2023
    for unit in ("left", "right"):
        assert rig.sup.apply_text(unit, "SERVO ON ON") == ""
        assert rig.sup.apply_text(unit, "START ON ON") == ""
    set_velocity(rig.sup, "left", 50, 0, source=present(rig.sup, "left"))
    set_velocity(rig.sup, "right", 100, 0, source=present(rig.sup, "right"))
    rig.run(3.0)
    log = tmp_path / "both.log"
    record_traffic(rig, log)
    guessed, err = decoded([str(log)], capsys)
    assert err == [
        "decode: address 1 looks like a 2021 drive (no --config): guessed",
        "decode: address 3 looks like a 2023 drive (no --config): guessed",
    ]
    cfg = tmp_path / "two.yaml"
    cfg.write_text(TWO_UNITS.replace("channel: t", "channel: can0"))
    known, err = decoded([str(log), "--config", str(cfg)], capsys)
    assert err == []  # told: nothing guessed
    swapped = tmp_path / "swapped.yaml"  # another robot's file: the generations the other way
    swapped.write_text(
        TWO_UNITS.replace("channel: t", "channel: can0")
        .replace('protocol: "2023", ', "")
        .replace("abh3_id: 1,", 'abh3_id: 1, protocol: "2023",')
    )
    _, err = decoded([str(log), "--config", str(swapped)], capsys)
    assert err == [
        f"decode: address {a} on can0 looks like a {traffic} drive in both.log, but "
        f"{swapped} says {filed}: decoded as the file says — was the recording made with "
        "this file? (without --config each address is decoded as its traffic shows)"
        for a, traffic, filed in ((1, 2021, 2023), (3, 2023, 2021))
    ]
    assert len(guessed) == len(known) == len(rig.timeline.frames)
    for g, k in zip(guessed, known, strict=True):  # the same reading, less the unit names
        assert {**g, "unit": None} == {**k, "unit": None}
    replies = {r["abh3_id"]: r for r in guessed if r["kind"] == "dp0_reply"}
    assert replies[1]["protocol"] == "2021" and replies[1]["values"]["vel_y"] == 50.0
    assert replies[3]["protocol"] == "2023" and replies[3]["values"]["vel_ay"] == 100.0
    assert "AY_READY" in replies[3]["flags"]["control"]  # read in the 2023 layout
    # what AY/BX are, from each drive's own control word: drive 1 travels, drive 3 is motors
    commands = {r["abh3_id"]: r for r in guessed if r["kind"] == "dp0_command"}
    assert (commands[1]["axes"], commands[3]["axes"], replies[3]["axes"]) == ("Y/X", "A/B", "A/B")
    assert "axes" not in replies[1]  # a 2021 reply names A, B, Y and X itself
    text = list(decode_file(log, None, as_json=False, report=lambda _: None))
    assert any(" dp0_command  axes=Y/X cmd_ay=50.0 cmd_bx=0.0 " in t for t in text)


@pytest.mark.wallclock
def test_decode_says_when_a_guess_is_uncertain_or_impossible(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "idle.log"
    log.write_text(
        "(1.000000) can0 00EF0102#0000000070700000 T\n"  # an idle drive: a zero reply
        "(1.001000) can0 00EF0201#0000000000000000 R\n"
        "(1.002000) can0 00FF2805#0000000000000000 R\n"  # address 5: broadcast 0 only
    )
    _, err = decoded([str(log)], capsys)
    assert err == [
        "decode: address 1 looks like a 2021 drive "
        "(no --config; idle replies read alike in both): guessed",
        "decode: address 5 sent no DP0 reply to tell its generation (no --config): decoded as 2021",
    ]
