"""The pieces of a bus shared between processes, without the processes: the echo filter,
``simulate.external``, and which buses ``abh3 simulate`` accepts."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.interfaces import shared_bus
from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.runtime import echo
from abh3_supervisor.runtime.bus_runtime import open_bus
from abh3_supervisor.runtime.echo import EchoFilter
from abh3_supervisor.runtime.simulating import Trace, simulated_buses


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def msg(arbitration_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True)


@pytest.fixture
def echoing() -> Iterator[tuple[EchoFilter, can.BusABC, Clock]]:
    """Our bus, which hears itself (receive_own_messages), and another host on it."""
    clock = Clock()
    ours = EchoFilter(
        can.Bus(interface="virtual", channel="echo-test", receive_own_messages=True), clock=clock
    )
    other = can.Bus(interface="virtual", channel="echo-test")
    yield ours, other, clock
    ours.shutdown()
    other.shutdown()


def test_our_own_frames_never_come_back(echoing: tuple[EchoFilter, can.BusABC, Clock]) -> None:
    ours, other, _ = echoing
    ours.send(msg(0x18EF0102, b"\x01" * 8))
    assert other.recv(1.0) is not None  # the others hear it …
    assert ours.recv(0.05) is None  # … we do not
    assert ours.echoes_dropped == 1


def test_our_copies_never_end_a_read_of_what_waits_behind_them(
    echoing: tuple[EchoFilter, can.BusABC, Clock],
) -> None:
    """The pump reads with ``recv(0)`` until it gets None: our copies first in the queue
    must not stop it before another host's frame behind them."""
    ours, other, _ = echoing
    ours.send(msg(0x18EF0102, b"\x01" * 8))
    ours.send(msg(0x18EF0102, b"\x02" * 8))
    other.send(msg(0x18EF0302, b"\x09" * 8))
    got = ours.recv(0)
    assert got is not None and bytes(got.data) == b"\x09" * 8
    assert ours.echoes_dropped == 2 and ours.recv(0) is None


def test_a_frame_equal_to_ours_from_another_host_still_shows(
    echoing: tuple[EchoFilter, can.BusABC, Clock],
) -> None:
    ours, other, _ = echoing
    frame = msg(0x18EF0102, b"\x00" * 8)
    other.send(frame)  # the other host's copy arrives before ours: it takes our place …
    ours.send(frame)
    heard = [ours.recv(0.05), ours.recv(0.05)]
    assert sum(m is not None for m in heard) == 1  # … and ours, left over, goes through
    other.send(msg(0x18EF0102, b"\x02" * 8))
    got = ours.recv(1.0)
    assert got is not None and bytes(got.data) == b"\x02" * 8  # a different frame: at once


def test_a_copy_that_never_came_is_forgotten(echoing: tuple[EchoFilter, can.BusABC, Clock]) -> None:
    ours, other, clock = echoing
    ours.inner.receive_own_messages = False  # type: ignore[attr-defined]  # the copy is lost
    frame = msg(0x18EF0102, b"\x05" * 8)
    ours.send(frame)
    clock.t += echo.EXPIRY_S + 0.1
    other.send(frame)
    assert ours.recv(1.0) is not None  # no longer mistaken for our copy
    assert ours.echoes_dropped == 0


def bus_file(interface: str, channel: str, simulate: str = "true") -> str:
    return f"""
buses:
  b: {{interface: {interface}, channel: "{channel}", simulate: {simulate}}}
units:
  - {{name: left, abh3_id: 1}}
"""


@pytest.mark.parametrize(
    ("interface", "channel", "simulate", "external"),
    [
        ("udp_multicast", "239.74.163.2", "true", True),  # a bus made for processes
        ("udp_multicast", "239.74.163.2", "{external: false}", False),
        ("socketcan", "vcan0", "true", False),  # in-process unless told
        ("socketcan", "vcan0", "{external: true}", True),
        ("virtual", "x", "true", False),
    ],
)
def test_where_the_simulated_drives_run(
    interface: str, channel: str, simulate: str, external: bool
) -> None:
    config = parse_config(bus_file(interface, channel, simulate))
    assert config.buses["b"].simulate is not None
    assert config.buses["b"].simulate.external is external


@pytest.mark.parametrize(
    ("interface", "channel", "says"),
    [
        ("virtual", "x", "python-can's virtual bus does not leave a process"),
        ("socketcan", "can0", "socketcan can0 may carry real drives"),
        ("pcan", "PCAN_USBBUS1", "may carry real drives"),
    ],
)
def test_simulate_refuses_a_bus_real_drives_may_be_on(
    interface: str, channel: str, says: str
) -> None:
    config = parse_config(bus_file(interface, channel))
    with pytest.raises(Abh3Error, match=says):
        simulated_buses(config)


def test_simulate_takes_a_shared_bus_and_names_a_missing_one() -> None:
    config = parse_config(bus_file("socketcan", "vcan1"))
    assert simulated_buses(config) == ["b"]
    with pytest.raises(Abh3Error, match=r"--bus main: no such bus \(buses: b\)"):
        simulated_buses(config, ["main"])
    real = parse_config(bus_file("socketcan", "vcan1", "false"))
    with pytest.raises(Abh3Error, match="no bus of the file has `simulate:`"):
        simulated_buses(real)


def test_open_bus_filters_echoes_where_the_interface_echoes() -> None:
    config = parse_config(
        bus_file("virtual", "echo-open", "false").replace(
            "simulate: false", "simulate: false, options: {receive_own_messages: true}"
        )
    )
    bus = open_bus(config.buses["b"])
    try:
        assert isinstance(bus, EchoFilter)
    finally:
        bus.shutdown()
    plain = open_bus(parse_config(bus_file("virtual", "echo-plain", "false")).buses["b"])
    try:
        assert not isinstance(plain, EchoFilter)
    finally:
        plain.shutdown()


def test_abh3_simulate_on_a_virtual_bus_is_a_usage_error(tmp_path: Path) -> None:
    path = tmp_path / "v.yaml"
    path.write_text(bus_file("virtual", "x"))
    done = subprocess.run(
        [sys.executable, "-m", "abh3_supervisor", "simulate", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2
    assert "does not leave a process" in done.stderr and "Traceback" not in done.stderr


def test_a_trace_on_a_full_disk_ends_the_trace_not_the_drives(
    caplog: pytest.LogCaptureFixture,
) -> None:
    trace = Trace(Path("/dev/full"), 0.0)
    event = {"t": 1.0, "unit": "left", "event": "moving", "velocity": [1.0, 1.0]}
    trace.write([event] * 10_000)  # more than a buffer's worth: the write fails …
    trace.write([event])  # … once said, then nothing more is tried
    trace.close()
    assert sum("the trace ends here" in r.message for r in caplog.records) == 1


def test_only_a_vcan_device_counts_as_a_virtual_socketcan_bus() -> None:
    assert shared_bus("socketcan", "vcan0") and shared_bus("socketcan", "vcan12")
    assert not shared_bus("socketcan", "vcanx") and not shared_bus("socketcan", "vcan-real")
