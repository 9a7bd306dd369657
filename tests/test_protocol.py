"""Codec tests with literal byte vectors; the vendor sample values of protocol doc §8."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from abh3_supervisor.errors import CodecError
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.classify import AddressBook, Direction, Kind, classify
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.protocol.scaling import ANALOG, CURRENT, LOAD, SUPPLY_VOLTAGE, VELOCITY


class TestIds:
    def test_seed_default_identifiers(self) -> None:
        assert ids.dp0_command_id(1, 2) == 0x00EF0102
        assert ids.dp0_reply_id(1, 2) == 0x00EF0201
        assert ids.request_id(1, 2) == 0x00EA0102
        assert ids.request_id(ids.ADDR_ALL, 2) == 0x00EAFF02
        assert [ids.broadcast_id(1, 5, n) for n in (0, 6)] == [0x00FF2801, 0x00FF2E01]

    def test_priority_goes_in_bits_26_to_28(self) -> None:
        assert ids.dp0_command_id(1, 2, priority=7) == 0x1CEF0102
        assert ids.dp0_command_id(1, 2, priority=3) == 0x0CEF0102

    def test_round_trip_and_match_ignoring_priority(self) -> None:
        cid = ids.CanId.from_int(0x18EF0201)
        assert (cid.priority, cid.dp, cid.pf, cid.ps, cid.sa) == (6, 0, 0xEF, 0x02, 0x01)
        assert cid.to_int() == 0x18EF0201
        assert ids.without_priority(0x18EF0201) == ids.without_priority(0x00EF0201)


class TestScaling:
    def test_round_to_nearest_not_truncate(self) -> None:
        # 100 / 0.2 = 499.99999999999994 in floating point: truncation sends 499
        assert VELOCITY.to_raw(100.0) == (500, False)
        assert VELOCITY.to_raw(-2.6) == (-13, False)
        assert CURRENT.to_raw(12.35) == (1235, False)

    def test_clamps_to_the_wire_range_and_says_so(self) -> None:
        assert VELOCITY.to_raw(7000) == (32767, True)
        assert VELOCITY.to_raw(-7000) == (-32768, True)
        assert CURRENT.to_raw(400) == (32767, True)
        assert VELOCITY.maximum == pytest.approx(6553.4)

    @pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
    def test_refuses_nan_and_infinity(self, bad: float) -> None:
        with pytest.raises(CodecError, match="not a finite number"):
            VELOCITY.to_raw(bad)

    def test_refuses_non_numbers(self) -> None:
        with pytest.raises(CodecError, match="expected a number"):
            VELOCITY.to_raw("5")  # type: ignore[arg-type]

    def test_physical_values_have_no_binary_noise(self) -> None:
        assert VELOCITY.to_physical(-13) == -2.6
        assert SUPPLY_VOLTAGE.to_physical(237) == 23.7
        assert ANALOG.to_physical(21) == 0.21


class TestFrames:
    def test_dp0_command_bytes(self) -> None:
        data = frames.encode_dp0_command(500, -100, 0x00073073)
        assert data == bytes.fromhex("f4019cff73300700")
        cmd = frames.decode_dp0_command(data, Generation.G2021)
        assert cmd == frames.Dp0Command(100.0, -20.0, 0x00073073)

    @pytest.mark.parametrize("layout", [flags.LAYOUT_2021, flags.LAYOUT_2023])
    def test_dp0_command_in_torque_mode_decodes_as_current(self, layout: flags.Layout) -> None:
        data = frames.encode_dp0_command(1000, 0, layout.torque.both)
        cmd = frames.decode_dp0_command(data, layout.generation)
        assert isinstance(cmd, frames.Dp0Command)
        assert (cmd.cmd_ay, cmd.ay_is_current, cmd.bx_is_current) == (10.0, True, True)
        # the other generation reads those bits differently: not torque there
        other = {"2021": Generation.G2023, "2023": Generation.G2021}[layout.generation]
        cmd = frames.decode_dp0_command(data, other)
        assert isinstance(cmd, frames.Dp0Command) and not cmd.ay_is_current

    def test_dp0_reply_both_generations(self) -> None:
        old = bytes.fromhex("f3ff0000faff0d00")
        assert frames.decode_dp0_reply(old, Generation.G2021) == frames.Dp0Reply2021(
            -2.6, 0.0, -1.2, 2.6
        )
        new = bytes.fromhex("f3ff0a0070000708")
        assert frames.decode_dp0_reply(new, Generation.G2023) == frames.Dp0Reply2023(
            -2.6, 2.0, 0x08070070
        )

    def test_requests(self) -> None:
        assert frames.encode_request(frames.PGN_DP0) == bytes([0x00, 0xEF, 0x00])
        assert frames.encode_request(frames.broadcast_pgn(5, 3)) == bytes([0x2B, 0xFF, 0x00])
        request = frames.decode_request(bytes([0x2B, 0xFF, 0x00]))
        assert isinstance(request, frames.Request)
        assert request.broadcast == (5, 3) and not request.is_dp0

    def test_vendor_sample_broadcast_0_before_commands(self) -> None:
        data = bytes.fromhex("0000400000004000")
        assert frames.decode_broadcast(0, data, Generation.G2021) == frames.Brd0(
            0x00400000, 0x00400000
        )
        assert flags.FAULT.names(0x00400000) == ["CAN_COMM_ERROR"]

    def test_vendor_sample_broadcast_1(self) -> None:
        data = bytes.fromhex("70000708c3000000")
        brd = frames.decode_broadcast(1, data, Generation.G2021)
        assert brd == frames.Brd1(io=0xC3, control=0x08070070)
        assert flags.LAYOUT_2021.control.names(0x08070070)[-1] == "TRAVEL_MODEL"
        assert flags.LAYOUT_2021.io.names(0xC3) == ["ERROR", "ALARM", "ERROR_CODE0", "ERROR_CODE1"]
        # the 2023 protocol swaps the words: I/O first, then the input flags
        assert frames.decode_broadcast(1, data, Generation.G2023) == frames.Brd1(
            io=0x08070070, inputs=0xC3
        )

    def test_vendor_sample_broadcasts_2_to_6(self) -> None:
        g = Generation.G2021
        assert frames.decode_broadcast(2, bytes.fromhex("00000000f3ff0000"), g) == frames.Brd2(
            0.0, 0.0, -2.6, 0.0
        )
        brd3 = frames.decode_broadcast(3, bytes.fromhex("0000000006000000"), g)
        assert isinstance(brd3, frames.Brd3)
        assert (brd3.load_a, brd3.load_a_raw) == (6.0, 6)  # spec 1 %/LSB; C sample says 0.6
        assert frames.decode_broadcast(4, bytes.fromhex("eb290200c3920600"), g) == frames.Brd4(
            141803, 430787
        )
        assert frames.decode_broadcast(5, bytes.fromhex("15000e00ed00ed00"), g) == frames.Brd5(
            0.21, 0.14, 23.7, 23.7
        )
        brd6 = frames.decode_broadcast(6, struct.pack("<ff", 0.011930, 0.106096), g)
        assert isinstance(brd6, frames.Brd6)
        assert brd6.monitor0 == pytest.approx(0.011930)
        assert brd6.monitor1 == pytest.approx(0.106096)

    def test_encoders_round_trip(self) -> None:
        g = Generation.G2021
        assert frames.encode_words(0x00400000, 0x00400000) == bytes.fromhex("0000400000004000")
        assert frames.encode_pulses(141803, 430787) == bytes.fromhex("eb290200c3920600")
        assert frames.encode_int16x2_uint16x2(21, 14, 237, 237) == bytes.fromhex("15000e00ed00ed00")
        load = LOAD.to_raw(6.0)[0]
        brd3 = frames.decode_broadcast(3, frames.encode_int16x2_uint16x2(100, -100, load, 0), g)
        assert brd3 == frames.Brd3(1.0, -1.0, 6.0, 0.0, 6, 0)

    def test_broadcast_7_keeps_raw_bytes(self) -> None:
        assert frames.decode_broadcast(7, b"\x01\x02", Generation.G2023) == frames.Brd7(b"\x01\x02")

    def test_short_payloads_decode_to_unknown(self) -> None:
        assert frames.decode_dp0_command(b"\x00" * 7, Generation.G2021) == frames.Unknown(
            "DP0 command: 7 data bytes, expected 8"
        )
        assert isinstance(frames.decode_broadcast(4, b"", Generation.G2021), frames.Unknown)
        assert isinstance(frames.decode_request(b"\x00"), frames.Unknown)


class TestFlags:
    def test_every_bit_has_a_name_and_both_labels(self) -> None:
        for layout in flags.LAYOUTS.values():
            for word in layout.words.values():
                for bit in word.bits:
                    assert bit.name and bit.en and bit.ja
        assert len(flags.LAYOUT_2021.io.bits) == 32  # every I/O bit is defined
        assert flags.FAULT.labels(1 << 22, "ja") == ["CAN 通信異常"]

    def test_undefined_bits_are_still_shown(self) -> None:
        assert flags.FAULT.names(1 << 30) == ["bit30"]

    def test_data_select(self) -> None:
        assert flags.LAYOUT_2021.data_select(0x08070070) == (7, 7)
        assert flags.LAYOUT_2023.data_select(0x00007373) == (7, 7)


class TestClassify:
    book = AddressBook()

    def test_command_and_reply_told_apart_by_host_address(self) -> None:
        cmd = classify(0x00EF0102, frames.encode_dp0_command(0, 0, 0), True, self.book)
        assert (cmd.kind, cmd.direction, cmd.abh3, cmd.host) == (
            Kind.DP0_COMMAND,
            Direction.TO_DRIVE,
            1,
            2,
        )
        reply = classify(0x00EF0201, bytes(8), True, self.book)
        assert (reply.kind, reply.direction, reply.abh3, reply.host) == (
            Kind.DP0_REPLY,
            Direction.FROM_DRIVE,
            1,
            2,
        )

    def test_broadcast_group_and_packet(self) -> None:
        frame = classify(0x00FF2B01, bytes(8), True, self.book)
        assert (frame.kind, frame.group, frame.packet, frame.abh3) == (Kind.BROADCAST, 5, 3, 1)

    def test_generation_per_drive(self) -> None:
        book = AddressBook(generations={3: Generation.G2023})
        frame = classify(0x00EF0203, bytes.fromhex("0a000a0000000000"), True, book)
        assert frame.payload == frames.Dp0Reply2023(2.0, 2.0, 0)

    def test_foreign_frames_are_unknown_with_a_reason(self) -> None:
        assert classify(0x123, b"", False, self.book).kind is Kind.UNKNOWN
        assert classify(0x00EC0102, bytes(8), True, self.book).kind is Kind.TRANSPORT
        other = classify(0x18FEF100, bytes(8), True, self.book)
        assert other.kind is Kind.UNKNOWN and "0xFE" in str(other.payload)
        assert classify(0x01EF0102, bytes(8), True, self.book).kind is Kind.UNKNOWN

    @given(
        st.integers(min_value=0, max_value=0x1FFFFFFF),
        st.binary(max_size=8),
        st.booleans(),
    )
    def test_decoding_arbitrary_bytes_never_raises(
        self, arbitration_id: int, data: bytes, extended: bool
    ) -> None:
        frame = classify(arbitration_id, data, extended, self.book)
        assert frame.kind in Kind
