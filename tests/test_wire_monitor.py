"""The wire monitor itself, on hand-made frame sequences: each invariant is caught, a
clean sequence passes; and its tap sees the frames of the rig and of virtual buses."""

from __future__ import annotations

import struct

import can
import pytest

from abh3_supervisor.config import parse_config
from tests.support.rig import TWO_UNITS, Rig
from tests.support.wire_monitor import ESTOP_POWER_OFF_S, WireMonitor, is_param_write

HOST, DRIVE21, DRIVE23 = 2, 1, 3
SEL21, SEL23 = 0x00070070, 0x00007070  # data select 7 on both axes: the safe word
SERVO21, START21, BRAKE21 = 0x1001, 0x2002, 1 << 28
SERVO23, START23 = 0x0101, 0x0202
HOST_SIDE, DRIVE_SIDE = "host", "drive"


def dp0(drive: int, ay: int, bx: int, inputs: int) -> tuple[int, bytes]:
    return 0xEF << 16 | drive << 8 | HOST, struct.pack("<hhI", ay, bx, inputs)


def param_frames(drive: int, text: bytes) -> list[tuple[int, bytes]]:
    """A host → drive TelABH3 request over the transport: RTS, then its DT frames."""
    body = text.ljust(9, b"\x16")
    npk = -(-len(body) // 7)
    rts = bytes([0x10, len(body), 0, npk, 0xFF, 0x00, 0xEF, 0x00])
    dts = [bytes([i + 1]) + body[i * 7 : i * 7 + 7].ljust(7, b"\xff") for i in range(npk)]
    return [(0xEC << 16 | drive << 8 | HOST, rts)] + [
        (0xEB << 16 | drive << 8 | HOST, d) for d in dts
    ]


class Bus:
    """A monitor with one bus whose drives' generations are declared, on a hand clock."""

    def __init__(self) -> None:
        self.monitor = WireMonitor()
        self.t = 0.0
        self.monitor.bus("b", "b", lambda: self.t)
        self.monitor.declare("b", DRIVE21, "2021")
        self.monitor.declare("b", DRIVE23, "2023")
        self.monitor.buses["b"].drive_senders.add(DRIVE_SIDE)
        for drive in (DRIVE21, DRIVE23):  # each has answered: its generation can be known
            self.reply(drive, bytes(8), dt=0.0)

    def reply(self, drive: int, data: bytes, dt: float = 0.02) -> None:
        self.send((0xEF << 16 | HOST << 8 | drive, data), dt, sender=DRIVE_SIDE)

    def send(self, frame: tuple[int, bytes], dt: float = 0.02, sender: str = HOST_SIDE) -> None:
        self.t += dt
        self.monitor.frame("b", sender, *frame, self.t)

    def invariants(self) -> list[str]:
        return [v.invariant for v in self.monitor.violations]


def test_a_clean_run_passes() -> None:
    bus = Bus()
    for _ in range(3):
        bus.send(dp0(DRIVE21, 0, 0, SEL21))
    bus.send(dp0(DRIVE21, 0, 0, SEL21 | SERVO21 | BRAKE21))
    bus.send(dp0(DRIVE21, 500, -500, SEL21 | SERVO21 | START21 | BRAKE21))
    bus.send(dp0(DRIVE23, 300, 0, SEL23 | SERVO23 | START23))
    bus.send((0xEF << 16 | HOST << 8 | DRIVE21, bytes(8)), sender=DRIVE_SIDE)  # a reply
    bus.send(dp0(DRIVE21, 0, 0, SEL21))  # the stop
    bus.send(dp0(DRIVE23, 0, 0, SEL23))
    for frame in param_frames(DRIVE21, b"CP5000004000080F"):  # a write, SERVO off
        bus.send(frame)
    bus.monitor.closed("b", HOST_SIDE)
    bus.monitor.check()
    assert bus.monitor.commanded() == 2


def test_a_parameter_write_after_servo_on_is_caught() -> None:
    bus = Bus()
    bus.send(dp0(DRIVE23, 0, 0, SEL23 | SERVO23))
    for frame in param_frames(DRIVE23, b"CP5000004000080F"):
        bus.send(frame)
    assert bus.invariants() == ["servo_write"]
    assert "SERVO" in bus.monitor.violations[0].frame


def test_a_read_with_servo_on_and_the_serial_form_are_told_apart() -> None:
    assert is_param_write(b"FFFFCP5000004000080F\x16")
    assert not is_param_write(b"CP000095\x16")
    bus = Bus()
    bus.send(dp0(DRIVE23, 0, 0, SEL23 | SERVO23))
    for frame in param_frames(DRIVE23, b"CP000095"):  # reading is no write
        bus.send(frame)
    bus.monitor.check()


def test_servo_on_in_the_middle_of_a_write_is_caught() -> None:
    bus = Bus()
    frames = param_frames(DRIVE21, b"CP5000004000080F")
    bus.send(frames[0])
    bus.send(frames[1])
    bus.send(dp0(DRIVE21, 0, 0, SEL21 | SERVO21))
    for frame in frames[2:]:
        bus.send(frame)
    assert bus.invariants() == ["servo_write"]


@pytest.mark.parametrize(
    ("last", "caught"),
    [
        (dp0(DRIVE21, 0, 0, SEL21), False),
        (dp0(DRIVE21, 0, 0, SEL21 | BRAKE21), True),  # brake released
        (dp0(DRIVE21, 0, 0, SEL21 | SERVO21), True),
        (dp0(DRIVE21, 1, 0, SEL21), True),  # a setpoint
        (dp0(DRIVE23, 0, 0, SEL23 | 1 << 16), True),  # torque mode is a switch too
    ],
)
def test_the_last_command_before_the_bus_closes_is_the_safe_word(
    last: tuple[int, bytes], caught: bool
) -> None:
    bus = Bus()
    bus.send(dp0(DRIVE21, 400, 0, SEL21 | SERVO21 | START21))
    bus.send(dp0(DRIVE23, 400, 0, SEL23 | SERVO23 | START23))
    bus.send(dp0(DRIVE23, 0, 0, SEL23))
    bus.send(last)
    if last[0] >> 8 & 0xFF == DRIVE23:
        bus.send(dp0(DRIVE21, 0, 0, SEL21))
    bus.monitor.closed("b", HOST_SIDE)
    assert bus.invariants() == (["safe_exit"] if caught else [])


def test_the_2021_word_read_as_2023_would_not_be_safe() -> None:
    """§5: the layout follows the drive; 2021's safe word is torque and master/slave in 2023."""
    bus = Bus()
    bus.send(dp0(DRIVE23, 0, 0, SEL21))
    bus.monitor.closed("b", HOST_SIDE)
    assert bus.invariants() == ["safe_exit"]


def test_an_estop_zeroes_and_stops_at_once_and_powers_off_within_the_bound() -> None:
    bus = Bus()
    bus.send(dp0(DRIVE21, 400, 0, SEL21 | SERVO21 | START21 | BRAKE21))
    bus.monitor.estop()
    bus.send(dp0(DRIVE21, 0, 0, SEL21 | SERVO21 | BRAKE21))  # category 1: power kept a while
    bus.send(dp0(DRIVE21, 0, 0, SEL21 | SERVO21 | BRAKE21), dt=0.5)
    bus.send(dp0(DRIVE21, 0, 0, SEL21), dt=0.3)
    bus.monitor.check()
    bus.monitor.clear()
    bus.send(dp0(DRIVE21, 400, 0, SEL21 | SERVO21 | START21))
    bus.monitor.check()


@pytest.mark.parametrize(
    ("after", "dt"),
    [
        (dp0(DRIVE21, 100, 0, SEL21 | SERVO21), 0.02),  # a setpoint
        (dp0(DRIVE21, 0, 0, SEL21 | SERVO21 | START21), 0.02),  # START kept
        (dp0(DRIVE21, 0, 0, SEL21 | SERVO21), ESTOP_POWER_OFF_S + 0.2),  # SERVO too long
    ],
)
def test_an_estop_that_does_not_stop_is_caught(after: tuple[int, bytes], dt: float) -> None:
    bus = Bus()
    bus.send(dp0(DRIVE21, 400, 0, SEL21 | SERVO21 | START21))
    bus.monitor.estop()
    bus.send(after, dt=dt)
    assert bus.invariants() == ["estop"]


def test_no_switch_rises_while_estopped() -> None:
    bus = Bus()
    bus.send(dp0(DRIVE23, 0, 0, SEL23))
    bus.monitor.estop()
    bus.send(dp0(DRIVE23, 0, 0, SEL23))
    bus.send(dp0(DRIVE23, 0, 0, SEL23 | SERVO23))
    assert bus.invariants() == ["estop"]
    assert "switched on" in bus.monitor.violations[0].why


def test_nothing_moves_while_declared_held() -> None:
    bus = Bus()
    bus.send(dp0(DRIVE23, 0, 0, SEL23 | SERVO23 | START23))
    with bus.monitor.held(DRIVE23, "verification"):
        bus.send(dp0(DRIVE23, 0, 0, SEL23))
        bus.send(dp0(DRIVE21, 300, 0, SEL21 | SERVO21 | START21))  # another drive: free
        bus.monitor.check()
        bus.send(dp0(DRIVE23, 100, 0, SEL23))
    assert bus.invariants() == ["hold"]


def test_malformed_frames_are_caught_and_replies_are_not_commands() -> None:
    bus = Bus()
    bus.send((dp0(DRIVE21, 0, 0, SEL21)[0], b"\x00" * 6))
    bus.send(dp0(DRIVE21, 0, 0, SEL21 | 1 << 10))  # bit 10 means nothing in 2021
    frames = param_frames(DRIVE21, b"CP000095")
    bus.send(frames[0])
    bus.send(frames[2])  # DT 2 before DT 1
    bus.send((0xEF << 16 | HOST << 8 | DRIVE21, b"\x01" * 3), sender=DRIVE_SIDE)
    bus.send((0xEA << 16 | DRIVE23 << 8 | HOST, b"\x00\xef"))  # a request of 2 bytes
    assert bus.invariants() == ["well_formed"] * 4


def test_an_allowed_invariant_is_not_reported() -> None:
    bus = Bus()
    bus.monitor.allowed.add("well_formed")
    bus.send((dp0(DRIVE21, 0, 0, SEL21)[0], b"\x00" * 6))
    bus.monitor.check()


def test_the_report_names_the_frame_time_unit_and_invariant() -> None:
    bus = Bus()
    bus.send(dp0(DRIVE21, 50, 0, SEL21 | SERVO21 | START21))
    bus.monitor.closed("b", HOST_SIDE)
    with pytest.raises(AssertionError) as failed:
        bus.monitor.check()
    text = str(failed.value)
    for part in ("[safe_exit]", "bus b", "t=0.0200", "unit 1", "setpoints 50/0", "SERVO START"):
        assert part in text


# ------------------------------------------------------------------ the tap


def test_the_tap_sees_the_rig(wire: WireMonitor) -> None:
    rig = Rig(parse_config(TWO_UNITS, "two.yaml"))
    rig.sup.apply_text("left", "SERVO ON ON")
    rig.run(0.2)
    assert wire.commanded() == 2  # both units of the rig, on its timeline
    assert not wire.violations


def test_the_tap_judges_a_virtual_bus_when_it_closes(wire: WireMonitor) -> None:
    host = can.Bus(interface="virtual", channel="wm", receive_own_messages=False)
    arbitration_id, data = dp0(DRIVE21, 0, 0, SEL21 | SERVO21 | START21)
    host.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True))
    assert wire.commanded() == 0  # address 1 is no drive the monitor knows of yet
    wire.declare(("virtual", "wm"), DRIVE21, "2021")
    host.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=True))
    host.shutdown()
    found, wire.violations = wire.violations, []
    # the drive never answered: SERVO and START before its generation could be known
    assert [v.invariant for v in found] == ["identity", "safe_exit"]


def test_a_resend_the_drive_asks_for_is_well_formed_and_still_a_write() -> None:
    bus = Bus()
    frames = param_frames(DRIVE23, b"CP5000004000080F")
    for frame in frames[:3]:
        bus.send(frame)
    bus.monitor.check()
    bus.send(dp0(DRIVE23, 0, 0, SEL23 | SERVO23))
    for frame in frames[2:]:  # the CTS asked again from DT 2
        bus.send(frame)
    assert bus.invariants() == ["servo_write"]


def test_energy_before_a_drive_ever_answered_is_caught_and_the_probe_is_not() -> None:
    monitor = WireMonitor()
    monitor.bus("b", "b", lambda: 0.0)
    monitor.declare("b", DRIVE23, "2023")
    monitor.frame("b", HOST_SIDE, *dp0(DRIVE23, 0, 0, 0x70), 0.01)  # the identity probe
    assert not monitor.violations
    monitor.frame("b", HOST_SIDE, *dp0(DRIVE23, 0, 0, SEL23), 0.02)  # 2021's B SERVO+START
    assert [v.invariant for v in monitor.violations] == ["identity"]


def test_a_drive_that_dropped_its_servo_and_comes_back_on_unasked_is_a_restart() -> None:
    bus = Bus()
    on = SEL23 | SERVO23 | START23
    bus.send(dp0(DRIVE23, 0, 0, on))
    bus.reply(DRIVE23, struct.pack("<hhI", 0, 0, on))  # it reports SERVO on
    bus.reply(DRIVE23, struct.pack("<hhI", 0, 0, SEL23))  # rebooted: off, still commanded
    bus.send(dp0(DRIVE23, 0, 0, on))
    assert not bus.invariants()
    bus.reply(DRIVE23, struct.pack("<hhI", 0, 0, on))  # on again: nobody switched it off
    assert bus.invariants() == ["no_restart"]


def test_servo_given_off_then_on_again_after_a_drop_is_the_operators_act() -> None:
    bus = Bus()
    on = SEL23 | SERVO23 | START23
    bus.send(dp0(DRIVE23, 0, 0, on))
    bus.reply(DRIVE23, struct.pack("<hhI", 0, 0, on))
    bus.reply(DRIVE23, struct.pack("<hhI", 0, 0, SEL23))
    bus.send(dp0(DRIVE23, 0, 0, SEL23))  # the host forgot it
    bus.send(dp0(DRIVE23, 0, 0, on))  # the operator switched it on again
    bus.reply(DRIVE23, struct.pack("<hhI", 0, 0, on))
    bus.monitor.check()


def test_motion_to_one_drive_while_its_robot_partner_is_silent_or_off_is_caught() -> None:
    """The robot invariant on the rig: a two-drive robot whose wheels the simulator knows;
    the host (here the test, writing frames itself) commands one drive while the other
    has not answered for longer than its command-zero timeout."""
    rig = Rig(parse_config(TWO_UNITS.replace("units:", ROBOT_UNITS), "two.yaml"))
    monitor = WireMonitor()
    watch = monitor.bus("b", "b", lambda: rig.timeline.now)
    monitor.drives("b", rig.sim, DRIVE_SIDE)
    watch.drive_senders.add(DRIVE_SIDE)
    for drive in (DRIVE21, DRIVE23):
        monitor.frame("b", DRIVE_SIDE, 0xEF << 16 | HOST << 8 | drive, bytes(8), 0.0)
    monitor.frame("b", HOST_SIDE, *dp0(DRIVE21, 500, 0, SEL21 | SERVO21 | START21), 0.05)
    assert not monitor.violations  # within the slack of its report
    monitor.frame("b", HOST_SIDE, *dp0(DRIVE21, 500, 0, SEL21 | SERVO21 | START21), 0.2)
    assert [v.invariant for v in monitor.violations] == ["robot"]  # 3 reported all SERVO off
    assert "drive 3 of its robot has reported every SERVO off" in monitor.violations[0].why
    monitor.violations.clear()
    monitor.frame(
        "b", DRIVE_SIDE, 0xEF << 16 | HOST << 8 | DRIVE23, struct.pack("<hhI", 0, 0, SERVO23), 0.02
    )
    monitor.frame("b", HOST_SIDE, *dp0(DRIVE21, 500, 0, SEL21 | SERVO21 | START21), 0.03)
    assert not monitor.violations  # both answer, both on
    monitor.frame("b", HOST_SIDE, *dp0(DRIVE21, 500, 0, SEL21 | SERVO21 | START21), 0.9)
    assert [v.invariant for v in monitor.violations] == ["robot"]  # 3 silent past 0.5 s
    assert "has not answered for" in monitor.violations[0].why


ROBOT_UNITS = """robots:
  - name: rover
    track_m: 0.5
    diameter_m: 0.2
    wheels:
      - {unit: left, axis: A, side: left}
      - {unit: right, axis: A, side: right}
units:"""


def test_a_setpoint_after_its_owner_left_is_caught_after_one_period() -> None:
    bus = Bus()
    moving = dp0(DRIVE23, 300, 0, SEL23 | SERVO23 | START23)
    bus.send(moving)
    with bus.monitor.unowned(DRIVE23, bus.t):
        bus.send(moving, dt=0.05)  # the frame already on its way: within the slack
        assert not bus.invariants()
        bus.send(moving, dt=0.1)
        assert bus.invariants() == ["ownership"]
        bus.monitor.violations.clear()
        bus.send(dp0(DRIVE23, 0, 0, SEL23 | SERVO23 | START23))  # zero: as it must be
    bus.monitor.check()
