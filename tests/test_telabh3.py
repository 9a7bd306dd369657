"""The TelABH3 codec against the reference's byte vectors (params reference §1.1–1.2)."""

from __future__ import annotations

import contextlib
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from abh3_supervisor.errors import CodecError
from abh3_supervisor.params.telabh3 import (
    Checksum,
    Command,
    Reply,
    Request,
    TelFormat,
    checksum,
    decode_reply,
    decode_request,
    encode_reply,
    pack_float,
    unpack_float,
)

SERIAL = TelFormat(header=True)


@pytest.mark.parametrize(
    ("text", "total"),
    [
        ("FFFFCP0000", 0x95),
        ("FFFFCM1012", 0x94),
        ("FFFFCP500000400008", 0x04),
        ("FFFFBI0002", 0x9B),
    ],
)
def test_checksum_vectors(text: str, total: int) -> None:
    assert checksum(text) == total


def test_request_strings_in_each_format() -> None:
    read = Request(Command.PARAM, 0)
    assert read.text(SERIAL) == "FFFFCP000095"
    assert read.text() == "CP000095"  # the maker's DLL example: no header, its checksum
    assert read.text(TelFormat(False, Checksum.AS_SENT)) == "CP0000AD"  # §1.3: 0xAD
    write = Request(Command.PARAM, 0x5000, 0x00400008)
    assert write.text(SERIAL) == "FFFFCP50000040000804"
    assert Request(Command.MONITOR, 0x1012).text(SERIAL) == "FFFFCM101294"
    assert Request(Command.IDENTITY, 2).text(SERIAL) == "FFFFBI00029B"


def test_transport_payload_is_syn_padded_to_nine_bytes() -> None:
    assert Request(Command.PARAM, 0).encode() == b"CP000095\x16"  # 8 + one SYN = 9
    assert Request(Command.PARAM, 0).encode(SERIAL) == b"FFFFCP000095\x16"
    short = Request(Command.IDENTITY, 2).encode(TelFormat(False, Checksum.AS_SENT))
    assert len(short) == 9 and short.endswith(b"\x16")


@pytest.mark.parametrize("fmt", [SERIAL, TelFormat(), TelFormat(False, Checksum.AS_SENT)], ids=str)
def test_the_drive_side_reads_every_format_and_knows_which(fmt: TelFormat) -> None:
    request = Request(Command.PARAM, 0x5000, 0x00400008)
    assert decode_request(request.encode(fmt) + b"\xff\xff") == (request, fmt)


def test_a_request_with_a_wrong_checksum_is_refused() -> None:
    with pytest.raises(CodecError, match="bad checksum"):
        decode_request(b"CP000096\x16")


def test_replies_read_write_identity_nak() -> None:
    # serial form: STX header ACK data SUM ETX, summing to zero
    body = "FFFF\x0600400008"
    serial = b"\x02" + f"{body}{checksum(body):02X}".encode() + b"\x03"
    assert decode_reply(serial).word == 0x00400008
    assert decode_reply(encode_reply(Reply(True, ""))) == Reply(True, "")
    ident = encode_reply(Reply(True, "1.2.3.4"), SERIAL)
    assert decode_reply(ident + b"\x16\xff") == Reply(True, "1.2.3.4")
    nak = decode_reply(encode_reply(Reply(False, ""), TelFormat(False, Checksum.AS_SENT)))
    assert not nak.ok
    with pytest.raises(CodecError, match="bad checksum"):
        decode_reply(b"\x060040000800")
    with pytest.raises(CodecError, match="ACK/NAK"):
        decode_reply(b"garbage")


@pytest.mark.parametrize(
    ("word", "value"),
    [(0x00400008, 800.0), (0x01E00001, 0.1), (0x01C00019, 0.25), (0x001FFFCE, -50.0)],
)
def test_packed_float_vectors(word: int, value: float) -> None:
    assert unpack_float(word) == value


def test_packed_float_encoding_is_the_makers_short_form() -> None:
    assert pack_float(800) == 0x00400008  # the maker's code writes CP5000 00400008
    assert pack_float(0.1) == 0x01E00001
    assert pack_float(0.25) == 0x01C00019
    # the maker's file holds −50 as mantissa −50 (0x001FFFCE); we write −5 × 10¹: both mean −50
    assert unpack_float(pack_float(-50)) == -50 and pack_float(-50) == 0x003FFFFB
    assert pack_float(0) == 0


def test_packed_float_special_codes() -> None:
    assert unpack_float(0x0FFFFF) == math.inf
    assert unpack_float(0x100000) == -math.inf
    assert math.isnan(unpack_float(1_000_000))
    assert pack_float(math.inf) == 0x0FFFFF and pack_float(-math.inf) == 0x100000
    assert math.isnan(unpack_float(pack_float(math.nan)))
    assert pack_float(1234567) == pack_float(1234570)  # six significant digits


@given(st.integers(-999_999, 999_999), st.integers(-12, 12))
def test_packed_float_round_trip(mantissa: int, power: int) -> None:
    value = float(f"{mantissa}e{power}")
    assert unpack_float(pack_float(value)) == value


@given(st.binary(max_size=40))
def test_garbage_is_a_codec_error_never_a_crash(payload: bytes) -> None:
    with contextlib.suppress(CodecError):
        decode_reply(payload)
    with contextlib.suppress(CodecError):
        decode_request(payload)
