"""``interface: wacousb`` against an independently written emulation of the adapter."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from abh3_supervisor.wacousb import WacoUsbBus, framing
from tests.wacousb_emulator import AdapterEmulator, crc_ccitt, firmware_frame

VECTOR_BODY = b"1800EF0102C309C30900000000"


def test_crc_and_framing_match_the_documented_vector() -> None:
    assert framing.crc16(VECTOR_BODY) == crc_ccitt(VECTOR_BODY) == 0xCC4B
    frame = framing.encode(0x00EF0102, bytes.fromhex("C309C30900000000"))
    assert frame == b"\x02" + VECTOR_BODY + b"CC4B\x03"
    decoded = framing.decode(frame[1:-1])
    assert (decoded.arbitration_id, decoded.data, decoded.extended) == (
        0x00EF0102,
        bytes.fromhex("C309C30900000000"),
        True,
    )


def test_framing_edge_cases() -> None:
    assert (
        framing.encode(0x123, b"", extended=False)
        == b"\x02" + b"0000000123" + (b"%04X" % framing.crc16(b"0000000123")) + b"\x03"
    )
    with pytest.raises(ValueError):
        framing.encode(0x800, b"", extended=False)
    with pytest.raises(ValueError):
        framing.encode(1, bytes(9))
    stamped = b"98" + b"00000000000004D2" + b"00EF0102" + b"C309C30900000000"
    body = stamped + b"%04X" % framing.crc16(stamped)
    assert framing.decode(body).timestamp == 1234  # FLAG bit 7: the DLL's timestamp form
    p = framing.Parser()
    good = framing.encode(0x00FF2801, bytes(8))
    out = p.feed(b"noise\x02" + b"1800EF" + good + b"\x02ZZ\x03" + good[:-5] + b"0000\x03")
    assert len(out) == 1  # the cut frame, the bad hex and the bad CRC are dropped
    assert (p.framing_errors, p.crc_errors) == (2, 1)


@pytest.fixture
def adapter(tmp_path: Path) -> Iterator[AdapterEmulator]:
    emu = AdapterEmulator(tmp_path / "ttyACM0", f"wacousb-{tmp_path.name}")
    yield emu
    emu.close()


@pytest.fixture
def peer(adapter: AdapterEmulator) -> Iterator[can.BusABC]:
    """Another node on the adapter's CAN bus."""
    bus = can.Bus(interface="virtual", channel=adapter.can_channel)
    yield bus
    bus.shutdown()


def open_bus(adapter: AdapterEmulator, **kwargs: Any) -> WacoUsbBus:
    bus = can.Bus(interface="wacousb", channel=str(adapter.link), **kwargs)
    assert isinstance(bus, WacoUsbBus)  # through python-can's `can.interface` entry point
    return bus


def test_opens_by_name_with_dtr_and_warns_the_bitrate_is_unchecked(
    adapter: AdapterEmulator, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING), open_bus(adapter, bitrate=1_000_000) as bus:
        assert bus._serial is not None and bus._serial.dtr and bus._serial.rts
    assert "cannot be checked" in caplog.text and "SW1 off, SW2 on" in caplog.text


def test_a_missing_device_is_a_clear_initialization_error(tmp_path: Path) -> None:
    with pytest.raises(can.CanInitializationError, match=r"cannot open .*ttyACM9.*plugged in"):
        can.Bus(interface="wacousb", channel=str(tmp_path / "ttyACM9"))


def test_frames_both_ways(adapter: AdapterEmulator, peer: can.BusABC) -> None:
    with open_bus(adapter) as bus:
        sent = [
            can.Message(arbitration_id=0x00EF0102, data=bytes.fromhex("C309C30900000000")),
            can.Message(arbitration_id=0x00EAFF02, data=b"\x00\xef\x00"),
            can.Message(arbitration_id=0x7FF, data=b"", is_extended_id=False),
        ]
        for msg in sent:
            bus.send(msg)
        got = [peer.recv(2) for _ in sent]
        assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got if m] == [
            (m.arbitration_id, bytes(m.data), m.is_extended_id) for m in sent
        ]
        assert adapter.host_frames[0] == b"\x02" + VECTOR_BODY + b"CC4B\x03"
        assert adapter.bad == [] and adapter.junk == 0

        for msg in sent:
            peer.send(msg)
        back = [bus.recv(2) for _ in sent]
        assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in back if m] == [
            (m.arbitration_id, bytes(m.data), m.is_extended_id) for m in sent
        ]
        with pytest.raises(can.CanOperationError, match="data frames only"):
            bus.send(can.Message(arbitration_id=1, is_remote_frame=True))


def test_bad_crc_and_bad_framing_are_counted_and_dropped(
    adapter: AdapterEmulator, peer: can.BusABC
) -> None:
    good = firmware_frame(can.Message(arbitration_id=0x00FF2801, data=bytes(range(8))))
    corrupt = good[:5] + (b"0" if good[5:6] != b"0" else b"1") + good[6:]  # one char flipped
    with open_bus(adapter) as bus:
        adapter.inject(corrupt + b"\x02XYZ\x03" + good)
        msg = bus.recv(2)
        assert msg is not None and bytes(msg.data) == bytes(range(8))
        assert (bus.crc_errors, bus.framing_errors) == (1, 1)
        assert bus.recv(0.05) is None  # nothing else came through


@pytest.mark.wallclock
def test_a_stalled_adapter_times_out_and_the_stream_stays_well_formed(
    adapter: AdapterEmulator, peer: can.BusABC
) -> None:
    with open_bus(adapter) as bus:
        adapter.stall()
        msg = can.Message(arbitration_id=0x00EF0102, data=bytes(8))
        accepted = 0
        with pytest.raises(can.CanOperationError, match=r"full|stalled"):
            for _ in range(100_000):  # the pty's buffer fills: bounded
                bus.send(msg, timeout=0)
                accepted += 1
        for _ in range(1000):  # the kernel may still move a few bytes on: until it stops
            t0 = time.monotonic()
            try:
                bus.send(msg, timeout=0.05)
            except can.CanOperationError as exc:
                assert "stalled" in str(exc) or "full" in str(exc)
                break
            accepted += 1
        else:
            pytest.fail("a stalled adapter kept taking frames")
        assert 0.04 < time.monotonic() - t0 < 1.0  # the write timeout holds, no longer
        adapter.stall(False)
        bus.send(can.Message(arbitration_id=0x00EF0102, data=b"\xff" * 8), timeout=2)
        assert adapter.wait_for(lambda: adapter.forwarded == accepted + 1)
        assert adapter.bad == [] and adapter.junk == 0  # a half-written frame was finished
        last = None
        while (m := peer.recv(0.5)) is not None:
            last = m
        assert last is not None and bytes(last.data) == b"\xff" * 8


def test_unplug_and_replug(adapter: AdapterEmulator, peer: can.BusABC) -> None:
    with open_bus(adapter, reopen_interval=0.01) as bus:
        bus.send(can.Message(arbitration_id=1, data=b"\x01"))
        assert adapter.wait_for(lambda: adapter.forwarded == 1)  # else unplugging loses it
        adapter.unplug()
        assert bus.recv(0.1) is None  # never raises: python-can's reader thread lives on
        assert not bus.connected and bus.vanished == 1
        with pytest.raises(can.CanOperationError, match="not connected"):
            bus.send(can.Message(arbitration_id=2, data=b"\x02"))
        adapter.plug()
        deadline = time.monotonic() + 5
        while not bus.connected and time.monotonic() < deadline:
            bus.recv(0.02)
        assert bus.connected and bus.reopens == 1
        bus.send(can.Message(arbitration_id=3, data=b"\x03"))
        peer.send(can.Message(arbitration_id=4, data=b"\x04"))
        msg = bus.recv(2)
        assert msg is not None and msg.arbitration_id == 4
    first = peer.recv(1)
    second = peer.recv(1)
    assert [m.arbitration_id for m in (first, second) if m] == [1, 3]


@pytest.mark.wallclock
def test_the_adapter_ring_holds_64_frames(adapter: AdapterEmulator, peer: can.BusABC) -> None:
    with open_bus(adapter) as bus:
        adapter.hold_output()
        for i in range(100):
            peer.send(can.Message(arbitration_id=0x100 + i, data=i.to_bytes(2, "little")))
        assert adapter.wait_for(lambda: len(adapter.to_host) + adapter.dropped == 100)
        adapter.hold_output(False)
        got = []
        while (m := bus.recv(0.3)) is not None:
            got.append(m.arbitration_id)
        assert got == [0x100 + i for i in range(64)] and adapter.dropped == 36
        assert bus.crc_errors == bus.framing_errors == 0


@pytest.mark.wallclock
def test_throughput_through_the_emulated_adapter(
    adapter: AdapterEmulator, peer: can.BusABC, capsys: pytest.CaptureFixture[str]
) -> None:
    n = 2000
    with open_bus(adapter) as bus:
        t0 = time.perf_counter()
        for i in range(n):
            bus.send(can.Message(arbitration_id=0x00EF0102, data=i.to_bytes(8, "little")))
        assert adapter.wait_for(lambda: adapter.forwarded == n, 30)
        out_rate = n / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        received = 0
        for burst in range(n // 50):  # bursts under the adapter's 64-frame ring
            for i in range(50):
                peer.send(
                    can.Message(
                        arbitration_id=0x00FF2801, data=(burst * 50 + i).to_bytes(8, "little")
                    )
                )
            for _ in range(50):
                assert bus.recv(2) is not None
                received += 1
        in_rate = n / (time.perf_counter() - t0)
    with capsys.disabled():
        print(
            f"\nwacousb emulated: host→bus {out_rate:.0f} frames/s, bus→host {in_rate:.0f} frames/s"
        )
    assert adapter.bad == [] and received == n and adapter.dropped == 0
