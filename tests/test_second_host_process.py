"""A second host on the bus (issue 32 item 3), with real processes: `abh3 simulate`, two
supervisors, a hand-made foreign host and python-can's own logger on one udp_multicast bus
in a network namespace with only ``lo``. Judged on the listener's frames and the drives'
own trace, not on what the supervisors say of themselves."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from abh3_supervisor.protocol import flags, frames, ids
from tests.support import shared
from tests.support.shared import SharedBus, Simulator, commands_to, wait_for

pytestmark = pytest.mark.wallclock

CONFIG = shared.MOVING_PAIR
# the hand-made host's word: SERVO on, START off, zero — neither ours moving nor our safe word
FOREIGN = frames.encode_dp0_command(0, 0, flags.LAYOUT_2021.servo.both)
HOST_SCRIPT = f"""
import time, can
bus = can.Bus(interface="udp_multicast", channel="{shared.GROUP}")
for _ in range(50):
    bus.send(can.Message(arbitration_id={ids.dp0_command_id(1, 2)}, data={FOREIGN!r},
                         is_extended_id=True))
    time.sleep(0.02)
bus.shutdown()
"""


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[SharedBus]:
    with shared.shared_bus(tmp_path, CONFIG) as bus:
        yield bus


def moving(msg: can.Message) -> bool:
    return bool(int.from_bytes(msg.data[0:2], "little", signed=True))


def turning(sim: Simulator, unit: str) -> None:
    first = sim.wait_event(unit, "moving", timeout=20)["t"]
    wait_for(
        f"{unit} turns for 0.3 s",
        lambda: any(e["t"] > first + 0.3 for e in sim.events(unit, "state")),
    )


def test_two_supervisors_stop_each_other_and_say_who(bus: SharedBus, tmp_path: Path) -> None:
    sim = bus.simulator()
    listener = bus.listener()
    listener.wait_started()
    sock = tmp_path / "a.sock"
    a = bus.supervisor("a", "--socket", str(sock))
    for unit in ("left", "right"):
        turning(sim, unit)
    started = time.time()
    b = bus.supervisor("b", "--no-socket")
    for sup in (a, b):
        sup.wait_log("another host (0x02) commands drive 0x01")
    for unit in ("left", "right"):
        sim.wait_event(unit, "standing", after=started)
    status = bus.abh3("status", "--connect", str(sock))
    assert status.returncode == 1 and "another host (0x02)" in status.stdout, status.stdout
    shared.window(1.0)  # and they stay stopped
    frames_ = listener.frames()
    for drive, unit in ((1, "left"), (3, "right")):
        ours = [m for m in commands_to(frames_, drive) if m.timestamp > started]
        first_b = next(m for m in ours if not moving(m))  # B's idle word: A's were moving
        last_moving = max(m.timestamp for m in ours if moving(m))
        assert last_moving - first_b.timestamp < 0.1  # A stopped within 100 ms
        assert not any(moving(m) for m in ours if m.timestamp > last_moving)
        assert not [e for e in sim.events(unit, "moving") if e["t"] > started]


def test_a_hand_made_host_is_met_with_our_safe_word_within_100_ms(bus: SharedBus) -> None:
    sim, listener, sup = bus.running()
    turning(sim, "left")
    host = bus.ns.run([sys.executable, "-c", HOST_SCRIPT], capture_output=True, timeout=30)
    assert host.returncode == 0, host.stderr
    sup.wait_log("another host (0x02) commands drive 0x01 (unit left)")
    frames_ = listener.frames()
    to_left = commands_to(frames_, 1)
    foreign = [m for m in to_left if bytes(m.data) == FOREIGN]
    assert len(foreign) == 50
    first = foreign[0].timestamp
    ours_after = [m for m in to_left if m.timestamp > first and bytes(m.data) != FOREIGN]
    assert ours_after and not moving(ours_after[0])  # our very next frame stops it …
    assert ours_after[0].timestamp - first < 0.1  # … within 100 ms
    assert not any(moving(m) for m in ours_after)  # and nothing of ours moves it again


def test_tools_refuse_a_bus_another_host_commands(bus: SharedBus) -> None:
    sim = bus.simulator()
    sup = bus.supervisor("sup", "--no-socket")
    turning(sim, "left")
    for args in (
        ("commission", str(bus.config), "left", "--yes", "--wheels-off-ground"),
        ("param", "-c", str(bus.config), "get", "left", "0x4117"),
        ("check", str(bus.config), "--drives"),
    ):
        done = bus.abh3(*args)
        assert done.returncode == 2, (args, done.stdout, done.stderr)
        assert "another host already commands a drive it would touch" in done.stderr
        assert "0x02" in done.stderr and "Traceback" not in done.stderr
    scan = bus.abh3("scan", "--interface", "udp_multicast", "--channel", shared.GROUP,
                    "--listen-only", "--listen", "1")  # fmt: skip
    assert scan.returncode == 0, scan.stderr
    assert "host 2 commands drive 1: " in scan.stdout, scan.stdout
    assert "host 2 commands drive 3: " in scan.stdout, scan.stdout
    assert "another host" not in sup.log()  # nothing was sent: the supervisor heard no one
