"""Host death, rehearsed on a wire (issue 32 item 2): the drives in ``abh3 simulate``, the
supervisor in a process of its own, an independent listener — all on one udp_multicast bus
in a network namespace with only ``lo``.

What stops a moving motor when its host dies is the drive's own command-zero timeout
(0x4117 = ``drive_timeout_ms``). Killed (-9), frozen (SIGSTOP) or cut off (the cable
pulled): the listener's last command and the drive's stop are ``drive_timeout_ms`` apart,
± one command period; a supervisor that comes back never restarts the motors by itself.
"""

from __future__ import annotations

import importlib.util
import json
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from tests.support import shared
from tests.support.shared import SharedBus, Simulator, commands_to, wait_for

pytestmark = pytest.mark.wallclock

TIMEOUT_S = 0.3  # drive_timeout_ms: the drives' 0x4117 as the file sets it
PERIOD_S = 0.02  # command_rate_hz 50
RAMP_S = 0.1  # 300 min⁻¹ at the simulator's 3000 min⁻¹/s
DRIVES = {"left": 1, "right": 3}
CONFIG = shared.MOVING_PAIR


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[SharedBus]:
    with shared.shared_bus(tmp_path, CONFIG) as bus:
        yield bus


def moving_for_a_while(sim: Simulator, *units: str) -> None:
    """Each unit's drive turning, seen in its trace for 0.3 s."""
    for unit in units:
        first = sim.wait_event(unit, "moving", timeout=20)["t"]

        def turned(unit: str = unit, first: float = first) -> bool:
            states = sim.events(unit, "state")
            return any(e["t"] > first + 0.3 and abs(e["velocity"][0]) > 250 for e in states)

        wait_for(f"{unit} turns for 0.3 s", turned)


def the_drive_stopped_itself(
    sim: Simulator, frames: list[can.Message], unit: str, since: float
) -> float:
    """The stop as the wire and the drive saw it: the listener's last command to the drive
    and the drive's own timeout ``drive_timeout_ms`` later, ± one period; still turning
    in between. Returns the last command's time."""
    timeout = next(e for e in sim.events(unit, "command_zero_timeout") if e["t"] >= since)
    last_t = max(
        m.timestamp for m in commands_to(frames, DRIVES[unit]) if m.timestamp < timeout["at"]
    )
    standing = next(e for e in sim.events(unit, "standing") if e["t"] >= since)
    assert timeout["at"] - last_t == pytest.approx(TIMEOUT_S, abs=PERIOD_S)
    assert timeout["at"] <= standing["t"] <= timeout["at"] + RAMP_S + 0.02  # its ramp down
    turning = [e for e in sim.events(unit, "state") if last_t < e["t"] < timeout["at"] - 0.01]
    assert turning and min(abs(e["velocity"][0]) for e in turning) > 250  # ran on until then
    return float(last_t)


def test_killed_with_minus_9_the_drives_stop_by_their_own_timeout(bus: SharedBus) -> None:
    sim, listener, sup = bus.running()
    moving_for_a_while(sim, "left", "right")
    killed = time.time()
    sup.proc.send_signal(signal.SIGKILL)
    sup.proc.wait(10)
    for unit in DRIVES:
        sim.wait_event(unit, "standing", after=killed)
    frames = listener.frames()
    for unit in DRIVES:
        last = the_drive_stopped_itself(sim, frames, unit, killed - 1)
        assert last <= killed + 0.005  # nothing was sent after the kill …
    assert not [
        m
        for m in frames
        if m.timestamp > killed + 0.005 and m.arbitration_id >> 8 & 0xFF in DRIVES.values()
    ]


def test_frozen_the_drives_stop_and_stay_stopped_when_it_wakes(bus: SharedBus) -> None:
    sim, listener, sup = bus.running()
    moving_for_a_while(sim, "left", "right")
    frozen = time.time()
    sup.proc.send_signal(signal.SIGSTOP)
    for unit in DRIVES:
        sim.wait_event(unit, "standing", after=frozen)
    woke = time.time()
    sup.proc.send_signal(signal.SIGCONT)
    for unit in DRIVES:
        sim.wait_event(unit, "commanded", after=woke)  # it sends again …
    sup.wait_log("the drive may have stopped on its command-zero timeout")
    shared.window(1.0)  # a second of commands after it
    for unit in DRIVES:  # … and nothing turns again: its setpoint was dropped
        assert not [e for e in sim.events(unit, "moving") if e["t"] > frozen]
    sup.proc.send_signal(signal.SIGTERM)
    assert sup.proc.wait(15) == 0  # a stop the drives confirmed
    frames = listener.frames()
    for unit in DRIVES:
        assert the_drive_stopped_itself(sim, frames, unit, frozen - 1) <= frozen + 0.005


def test_the_cable_pulled_the_drive_stops_and_stays_stopped_when_it_is_back(
    bus: SharedBus,
) -> None:
    sim, listener, sup = bus.running()
    moving_for_a_while(sim, "left", "right")
    assert sim.tell("unplug left") == "ok unplugged left"
    pulled = time.time()
    timeout = sim.wait_event("left", "command_zero_timeout", after=pulled)
    sim.wait_event("left", "standing", after=pulled)
    # it last heard the host just before the pull: its own timeout then, ± one period
    assert timeout["at"] - pulled == pytest.approx(TIMEOUT_S, abs=PERIOD_S + 0.01)
    sup.wait_log("unit left: OFFLINE")  # the host hears it no more
    assert not [e for e in sim.events("right", "standing")]  # the other drive ran on
    assert sim.tell("plug left") == "ok plugged left"
    plugged = time.time()
    sim.wait_event("left", "commanded", after=plugged)
    sup.wait_log("unit left: online")
    shared.window(1.0)  # a second of commands after it
    assert not [e for e in sim.events("left", "moving") if e["t"] > pulled]
    frames = listener.frames()
    assert commands_to(frames, 1)[-1].timestamp > plugged  # commanded all along


def test_a_drive_without_its_command_zero_timeout_is_refused_end_to_end(
    tmp_path: Path,
) -> None:
    text = CONFIG.replace("    simulate:\n", "    simulate:\n      params: {left: {0x4117: 0}}\n")
    with shared.shared_bus(tmp_path, text) as bus:
        sim = bus.simulator()
        check = bus.abh3("check", "--drives", str(bus.config))
        assert check.returncode == 1, check.stdout + check.stderr
        assert "CAN_COMMAND_ZERO_TIMEOUT  0 (off)" in check.stdout
        assert "MISMATCH" in check.stdout
        sup = bus.supervisor("sup", "--no-socket")
        sup.wait_log("unit left: drive 0x4117 CAN_COMMAND_ZERO_TIMEOUT = 0 (off)")
        sup.wait_log("unit left: the drive's CAN settings differ from the file (1 of 7): held")
        sim.wait_event("right", "moving", timeout=20)  # the other drive is fine: it runs
        shared.window(1.0)  # a second of the run
        assert not sim.events("left", "moving")  # never moved
        sup.proc.send_signal(signal.SIGTERM)
        assert sup.proc.wait(15) == 0


def test_the_documented_demo_shows_the_stop_300_ms_after_the_last_command(
    tmp_path: Path,
) -> None:
    """docs/simulator.md's demo, as a user runs it: its summary's lines."""
    shared.namespace_or_skip()
    path = Path(__file__).parents[1] / "docs" / "examples" / "host-death" / "demo.py"
    spec = importlib.util.spec_from_file_location("host_death_demo", path)
    assert spec is not None and spec.loader is not None
    demo = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(demo)
    lines = demo.demo(signal.SIGKILL, tmp_path)
    for unit in DRIVES:
        own = [line for line in lines if line.startswith(f"{unit}: its own timeout (0x4117)")]
        assert len(own) == 1, lines
        late = int(own[0].rsplit("+", 1)[1].removesuffix(" ms"))
        assert abs(late - TIMEOUT_S * 1000) <= PERIOD_S * 1000, lines


def test_a_drive_whose_power_blips_comes_back_standing_and_switched_off(bus: SharedBus) -> None:
    """Power off and at once on again: the drive boots (1 s, silent), the supervisor sees
    it offline, and when it answers again nothing switches it on or moves it."""
    sim, _, sup = bus.running()
    moving_for_a_while(sim, "left", "right")
    assert sim.tell("power off left") == "ok power off left"
    assert sim.tell("power on left") == "ok power on left"
    back = time.time()
    sup.wait_log("unit left: OFFLINE")
    sup.wait_log("unit left: online", timeout=15)  # answers again after booting …
    shared.window(1.0)  # … and stays as it came back
    assert sim.tell("status") == "ok status"
    left, right = json.loads(sim.out.next()), json.loads(sim.out.next())
    assert left["unit"] == "left" and left["powered"]
    assert left["servo"] == [False, False] and left["start"] == [False, False]
    assert left["velocity"] == [0.0, 0.0]
    assert not [e for e in sim.events("left", "moving") if e["t"] > back]
    assert right["unit"] == "right" and right["servo"] == [True, True]  # it ran on
    assert not sim.events("right", "standing")
