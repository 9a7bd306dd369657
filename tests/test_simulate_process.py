"""`abh3 simulate` as a process of its own (issue 32 item 1): `scan`, `param -c` and
`commission` reach its drives through the file, exactly as they would real ones; its
recording holds each frame once; it stops cleanly on SIGTERM."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from tests.support import shared
from tests.support.shared import SharedBus

pytestmark = pytest.mark.wallclock

CONFIG = f"""
buses:
  shared:
    interface: udp_multicast
    channel: {shared.GROUP}
    simulate: true
units:
  - {{name: left, bus: shared, abh3_id: 1, command_rate_hz: 50, drive_timeout_ms: 300}}
  - {{name: right, bus: shared, abh3_id: 3, protocol: "2023", command_rate_hz: 50,
     drive_timeout_ms: 300}}
"""


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[SharedBus]:
    with shared.shared_bus(tmp_path, CONFIG) as bus:
        yield bus


def test_scan_param_and_commission_reach_the_simulated_drives_as_real_ones(
    bus: SharedBus, tmp_path: Path
) -> None:
    record = tmp_path / "simulator.log"
    sim = bus.simulator(extra=("--record", str(record)))
    scan = bus.abh3("scan", "--interface", "udp_multicast", "--channel", shared.GROUP)
    assert scan.returncode == 0, scan.stderr
    rows = {line.split()[0]: line.split() for line in scan.stdout.splitlines()[1:3]}
    assert rows["1"][1] == "2021" and rows["3"][1] == "2023"
    got = bus.abh3("param", "-c", str(bus.config), "get", "left", "0x4117")
    assert got.returncode == 0, got.stderr
    assert got.stdout.split()[:3] == ["0x4117", "CAN_COMMAND_ZERO_TIMEOUT", "300"]
    report = tmp_path / "commission.html"
    done = bus.abh3(
        "commission", str(bus.config), "left", "--wheels-off-ground", "--yes",
        "--jog-s", "0.3", "--step-s", "0.3", "--report", str(report), timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "left: PASS" in done.stdout
    assert "opening udp_multicast 239.74.163.2 as a real bus" in done.stderr
    sim.proc.send_signal(signal.SIGTERM)
    assert sim.proc.wait(15) == 0
    frames = list(can.LogReader(str(record)))
    heard = [f for f in frames if f.is_rx]
    said = [f for f in frames if not f.is_rx]
    assert heard and said
    # the drives' own frames (source 1 or 3) never came back as heard ones: each frame once
    assert all(f.arbitration_id & 0xFF not in (1, 3) for f in heard)
    assert all(f.arbitration_id & 0xFF in (1, 3) for f in said)
