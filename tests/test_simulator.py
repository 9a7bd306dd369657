"""The simulated ABH3 answers as the drive does (protocol doc §3, §5, §6, §8)."""

from __future__ import annotations

import pytest

from abh3_supervisor.config import SimConfig, VelocityModel
from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.simulator import SimDrive

L21, L23 = flags.LAYOUT_2021, flags.LAYOUT_2023
SERVO_START = L21.servo.both | L21.start.both
SELECT_0 = 0x00070070  # written 7 on both axes = data set #0
assert L21.select(7, 7) == SELECT_0


def command(
    drive: SimDrive, t: float, ay: int = 0, bx: int = 0, inputs: int = 0, host: int = 2
) -> list[tuple[int, bytes]]:
    drive.on_frame(
        ids.dp0_command_id(drive.abh3_id, host), frames.encode_dp0_command(ay, bx, inputs), t
    )
    return drive.poll(t + 0.01)


def request(
    drive: SimDrive, t: float, pgn: int, dest: int | None = None
) -> list[tuple[int, bytes]]:
    drive.on_frame(
        ids.request_id(drive.abh3_id if dest is None else dest, 2), frames.encode_request(pgn), t
    )
    return drive.poll(t + 0.01)


def brd(drive: SimDrive, n: int, t: float) -> frames.Broadcast | frames.Unknown:
    ((arbitration_id, data),) = request(drive, t, frames.broadcast_pgn(drive.group, n))
    assert arbitration_id == ids.broadcast_id(drive.abh3_id, drive.group, n)
    return frames.decode_broadcast(n, data, drive.generation)


def run(drive: SimDrive, start: float, end: float, ay: int, bx: int, inputs: int) -> None:
    """Keep commands flowing every 20 ms, as the supervisor does."""
    t = start
    while t < end:
        command(drive, t, ay, bx, inputs)
        t += 0.02


def test_before_any_command_bit_22_is_set_in_error_and_alarm() -> None:
    drive = SimDrive(1)
    assert brd(drive, 0, 0.0) == frames.Brd0(0x00400000, 0x00400000)  # as §8 saw


def test_dp0_reply_goes_to_the_commanding_host() -> None:
    drive = SimDrive(1)
    ((arbitration_id, data),) = command(drive, 0.0, host=9)
    assert arbitration_id == ids.dp0_reply_id(1, 9)
    assert frames.decode_dp0_reply(data, Generation.G2021) == frames.Dp0Reply2021(0, 0, 0, 0)


def test_velocity_ramps_to_the_command_when_servo_and_start_are_on() -> None:
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1000))
    run(drive, 0.0, 0.2, 500, -250, SERVO_START | SELECT_0)  # 100 and −50 min⁻¹
    assert drive.vel == pytest.approx([100.0, -50.0])
    assert brd(drive, 0, 0.2) == frames.Brd0(0, 0)
    brd2 = brd(drive, 2, 0.2)
    assert brd2 == frames.Brd2(100.0, -50.0, 100.0, -50.0)


def test_ramp_rate_is_the_configured_acceleration() -> None:
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1000))
    run(drive, 0.0, 0.05, 5000, 5000, SERVO_START | SELECT_0)  # 1000 min⁻¹
    drive.advance(0.05)
    assert drive.vel[0] == pytest.approx(50.0)  # 1000 min⁻¹/s × 50 ms


@pytest.mark.parametrize(
    "inputs",
    [L21.start.both | SELECT_0, L21.servo.both | SELECT_0, SERVO_START],
    ids=["no servo", "no start", "select 0 = #7 & STOP"],
)
def test_gating_keeps_the_motor_still(inputs: int) -> None:
    drive = SimDrive(1)
    run(drive, 0.0, 0.3, 500, 0, inputs)
    assert drive.vel == [0.0, 0.0]


def test_travel_model_converts_y_x_to_the_motors() -> None:
    drive = SimDrive(1, model=VelocityModel.TRAVEL, cfg=SimConfig(accel=1e5))
    run(drive, 0.0, 0.1, 500, 100, SERVO_START | SELECT_0)  # Y 100, X 20
    assert drive.vel == pytest.approx([120.0, 80.0])
    reply = frames.decode_dp0_reply(
        command(drive, 0.1, 500, 100, SERVO_START | SELECT_0)[0][1], Generation.G2021
    )
    assert reply == frames.Dp0Reply2021(120.0, 80.0, 100.0, 20.0)
    control = brd(drive, 1, 0.1)
    assert isinstance(control, frames.Brd1) and control.control is not None
    assert control.control & L21.travel_model


def test_2023_generation_reply_and_broadcast_1() -> None:
    drive = SimDrive(
        1, generation=Generation.G2023, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e5)
    )
    word = 0x00007373  # the maker's v2.0 sample: servo + start + select 7 on both axes
    run(drive, 0.0, 0.1, 50, 0, word)
    _, data = command(drive, 0.1, 50, 0, word)[0]
    reply = frames.decode_dp0_reply(data, Generation.G2023)
    assert isinstance(reply, frames.Dp0Reply2023) and (reply.vel_ay, reply.vel_bx) == (10.0, 0.0)
    status = ["AY_READY", "AY_BUSY", "BX_READY", "BRAKE_RELEASE_OUT"]  # bits 25-31
    assert L23.control.names(reply.control & ~word) == status
    assert reply.control & word == word
    b1 = brd(drive, 1, 0.1)
    assert isinstance(b1, frames.Brd1) and b1.inputs == word and b1.control is None
    assert b1.io == 0  # 2023 I/O is the wired digital I/O; the simulator has none


def test_2023_drive_obeys_the_2023_layout_only() -> None:
    def drive_with(word: int, ay: int = 500, bx: int = 500) -> SimDrive:
        drive = SimDrive(
            1, generation=Generation.G2023, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e5)
        )
        run(drive, 0.0, 0.2, ay, bx, word)
        return drive

    both = drive_with(L23.servo.both | L23.start.both | L23.select(7, 7))
    assert both.vel == [100.0, 100.0]  # both wheels turn
    # the same request written in the 2021 layout: B/X servo and start stay off, and
    # select 7 on B lands on torque A/B and master/slave
    old = SERVO_START | SELECT_0
    assert L23.input.names(old) == [
        "AY_SERVO_ON",
        "AY_START",
        "AY_SELECT0",
        "AY_SELECT1",
        "AY_SELECT2",
        "BX_SELECT0",
        "BX_SELECT1",
        "AY_TORQUE",
        "BX_TORQUE",
        "MASTER_SLAVE",
    ]
    misread = drive_with(old)
    assert misread.vel[1] == 0.0  # the B/X axis never moves
    assert misread.control_word() & L23.torque.both == L23.torque.both  # torque mode


def test_command_zero_timeout_stops_and_raises_alarm_22_then_error_22() -> None:
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e5))
    run(drive, 0.0, 0.1, 500, 500, SERVO_START | SELECT_0)
    last = 0.08
    assert brd(drive, 0, last + 0.49) == frames.Brd0(0, 0)
    assert brd(drive, 0, last + 0.51) == frames.Brd0(0, flags.CAN_COMM_ERROR)
    drive.advance(last + 0.6)
    assert drive.vel == [0.0, 0.0]  # START went off: decelerating stop
    assert brd(drive, 0, last + 1.01) == frames.Brd0(flags.CAN_COMM_ERROR, flags.CAN_COMM_ERROR)
    # commands flowing again clear both (as §8 observed)
    run(drive, 1.2, 1.3, 0, 0, SERVO_START | SELECT_0)
    assert brd(drive, 0, 1.3) == frames.Brd0(0, 0)


def test_timeout_deadline_wakes_the_drive_on_time() -> None:
    drive = SimDrive(1)
    command(drive, 0.0)
    assert drive.next_deadline() == pytest.approx(0.5)


def test_latched_error_needs_reset_rising_edge_and_servo_goes_off() -> None:
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e5))
    run(drive, 0.0, 0.1, 500, 0, SERVO_START | SELECT_0)
    drive.inject_error(flags.FAULT.mask("A_OVERCURRENT"))
    run(drive, 0.1, 0.2, 500, 0, SERVO_START | SELECT_0)
    assert drive.vel[0] == 0.0  # an error turns the servo off
    assert brd(drive, 0, 0.2) == frames.Brd0(flags.FAULT.mask("A_OVERCURRENT"), 0)
    run(drive, 0.2, 0.3, 500, 0, SERVO_START | SELECT_0 | L21.error_reset)
    assert brd(drive, 0, 0.3) == frames.Brd0(0, 0)
    run(drive, 0.3, 0.4, 500, 0, SERVO_START | SELECT_0)
    assert drive.vel[0] == 0.0  # after reset the servo stays off until re-asserted
    run(drive, 0.4, 0.5, 500, 0, L21.start.both | SELECT_0)
    run(drive, 0.5, 0.6, 500, 0, SERVO_START | SELECT_0)
    assert drive.vel[0] == pytest.approx(100.0)


def reported_servo(drive: SimDrive, t: float) -> int:
    """The SERVO bits of the control word the drive reports: broadcast 1 in 2021, the DP0
    reply in 2023 (asked for with the request PGN, which commands nothing)."""
    lay = drive.layout
    if drive.generation is Generation.G2021:
        b1 = brd(drive, 1, t)
        assert isinstance(b1, frames.Brd1) and b1.control is not None
        return b1.control & lay.servo.both
    ((_, data),) = request(drive, t, frames.PGN_DP0)
    reply = frames.decode_dp0_reply(data, Generation.G2023)
    assert isinstance(reply, frames.Dp0Reply2023)
    assert bool(reply.control & lay.ready.both) == bool(reply.control & lay.servo.both)
    return reply.control & lay.servo.both


@pytest.mark.parametrize("generation", list(Generation))
def test_after_an_error_clears_the_servo_stays_off_until_the_host_cycles_servo(
    generation: Generation,
) -> None:
    """As a real drive (protocol doc §5, docs/hardware.md): the error's end never turns a
    motor back on; SERVO off, then on, does — per axis."""
    overcurrent = flags.FAULT.mask("A_OVERCURRENT")
    fault = Fault(FaultKind.ERROR_BITS, at_s=0.25, for_s=0.2, bits=overcurrent)
    drive = SimDrive(
        1,
        generation=generation,
        model=VelocityModel.MOTOR,
        cfg=SimConfig(accel=1e5),
        faults=(fault,),
    )
    lay = drive.layout
    running = lay.servo.both | lay.start.both | lay.select(7, 7)
    run(drive, 0.0, 0.2, 500, 500, running)
    assert reported_servo(drive, 0.2) == lay.servo.both
    run(drive, 0.2, 0.4, 500, 500, running)
    assert drive.error_word() == overcurrent and reported_servo(drive, 0.4) == 0
    run(drive, 0.46, 0.6, 500, 500, running)  # the error is gone, SERVO still asked for
    assert brd(drive, 0, 0.6) == frames.Brd0(0, 0)
    assert reported_servo(drive, 0.6) == 0  # and the servo stays off
    assert drive.vel == [0.0, 0.0]
    # SERVO off and on again on the A/Y axis only: that axis comes back, B/X stays off
    run(drive, 0.6, 0.64, 500, 500, running & ~lay.servo.ay)
    assert reported_servo(drive, 0.64) == 0
    run(drive, 0.64, 0.8, 500, 500, running)
    assert reported_servo(drive, 0.8) == lay.servo.ay
    assert drive.vel == [100.0, 0.0]
    run(drive, 0.8, 0.84, 500, 500, running & ~lay.servo.bx)
    run(drive, 0.84, 1.0, 500, 500, running)
    assert reported_servo(drive, 1.0) == lay.servo.both
    assert drive.vel == [100.0, 100.0]


def test_an_error_between_frames_trips_the_servo() -> None:
    """A scripted error that comes and goes while no frame arrives still trips the servo:
    the drive wakes when it starts."""
    fault = Fault(FaultKind.ERROR_BITS, at_s=0.5, for_s=0.01)
    quiet = SimConfig(error_timeout_ms=0, command_zero_timeout_ms=0)  # nothing else wakes it
    drive = SimDrive(1, cfg=quiet, faults=(fault,))
    command(drive, 0.0, 0, 0, SERVO_START | SELECT_0)
    assert drive.next_deadline() == pytest.approx(0.5) and drive.error_word() == 0
    assert drive.poll(drive.next_deadline()) == []
    assert drive.error_word() == 1 << 6
    assert reported_servo(drive, 0.6) == 0  # the fault has ended: the servo stays off


def test_the_reset_flow_error_reset_then_servo_cycle() -> None:
    """A latched error: the reset bit clears it and keeps the servo off even with SERVO
    on; SERVO off then on brings it back (what the TUI's `r` and `v` send)."""
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e5))
    running = SERVO_START | SELECT_0
    run(drive, 0.0, 0.1, 500, 0, running)
    drive.inject_error(flags.FAULT.mask("B_OVERCURRENT"))
    assert reported_servo(drive, 0.1) == 0
    run(drive, 0.1, 0.2, 500, 0, running)
    assert drive.error_word() == flags.FAULT.mask("B_OVERCURRENT")  # latched
    run(drive, 0.2, 0.22, 500, 0, running | L21.error_reset)
    run(drive, 0.22, 0.3, 500, 0, running)
    assert brd(drive, 0, 0.3) == frames.Brd0(0, 0) and reported_servo(drive, 0.3) == 0
    run(drive, 0.3, 0.32, 500, 0, running & ~L21.servo.both)
    run(drive, 0.32, 0.4, 500, 0, running)
    assert reported_servo(drive, 0.4) == L21.servo.both and drive.vel[0] == pytest.approx(100)
    # a reset sent with SERVO off needs no cycle: SERVO on afterwards is the rising edge
    drive.inject_error(flags.FAULT.mask("A_OVERCURRENT"))
    run(drive, 0.4, 0.42, 0, 0, (running & ~L21.servo.both) | L21.error_reset)
    run(drive, 0.42, 0.5, 500, 0, running)
    assert reported_servo(drive, 0.5) == L21.servo.both


def test_an_error_timeout_in_a_pause_keeps_the_servo_off_when_commands_return() -> None:
    """Error bit 22 (the drive's error timeout): it clears when commands flow again (§8),
    the servo does not come back on by itself."""
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e5))
    run(drive, 0.0, 0.1, 500, 0, SERVO_START | SELECT_0)
    assert drive.vel[0] == pytest.approx(100)
    assert brd(drive, 0, 1.2) == frames.Brd0(flags.CAN_COMM_ERROR, flags.CAN_COMM_ERROR)
    run(drive, 1.2, 1.4, 500, 0, SERVO_START | SELECT_0)
    assert brd(drive, 0, 1.4) == frames.Brd0(0, 0)
    assert reported_servo(drive, 1.4) == 0 and drive.vel == [0.0, 0.0]


def test_pulse_counting_and_clear() -> None:
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e9))
    run(drive, 0.0, 1.0, 300, 0, SERVO_START | SELECT_0)  # 60 min⁻¹ = 1 rev/s
    b4 = brd(drive, 4, 1.0)
    assert isinstance(b4, frames.Brd4) and b4.pulse_a == pytest.approx(4096, abs=2)
    run(drive, 1.0, 1.05, 300, 0, SERVO_START | SELECT_0 | L21.pulse_clear.ay)
    b4 = brd(drive, 4, 1.05)
    assert isinstance(b4, frames.Brd4) and b4.pulse_a < 300


def test_load_supply_and_monitor_values() -> None:
    drive = SimDrive(1, model=VelocityModel.MOTOR, cfg=SimConfig(accel=1e9))
    run(drive, 0.0, 0.1, 2000, 0, SERVO_START | SELECT_0)  # 400 min⁻¹
    b3, b5, b6 = brd(drive, 3, 0.1), brd(drive, 5, 0.1), brd(drive, 6, 0.1)
    assert isinstance(b3, frames.Brd3) and b3.load_a > b3.load_b > 0
    assert isinstance(b5, frames.Brd5) and (b5.analog0, b5.control_volt) == (0.21, 23.7)
    assert b5.main_volt < 23.7
    assert isinstance(b6, frames.Brd6) and b6.monitor0 == pytest.approx(0.4)


def test_group_addressing_and_requests_to_all() -> None:
    drive = SimDrive(1, group=5)
    assert request(drive, 0.0, frames.broadcast_pgn(4, 0)) == []  # another group
    assert len(request(drive, 0.0, frames.broadcast_pgn(5, 0), dest=ids.ADDR_ALL)) == 1
    assert request(drive, 0.0, frames.broadcast_pgn(5, 0), dest=2) == []  # another drive
    ((arbitration_id, _),) = request(drive, 0.0, frames.PGN_DP0)  # DP0 without a command
    assert arbitration_id == ids.dp0_reply_id(1, 2)


def test_fault_injection_silence_and_delay() -> None:
    drive = SimDrive(1, cfg=SimConfig(reply_latency_ms=0))
    drive.silent = True
    assert command(drive, 0.0) == []
    drive.silent = False
    drive.extra_delay = 0.05
    drive.on_frame(ids.dp0_command_id(1, 2), bytes(8), 1.0)
    assert drive.poll(1.04) == [] and len(drive.poll(1.05)) == 1


def test_periodic_modes() -> None:
    drive = SimDrive(
        1, cfg=SimConfig(dp0_period_ms=10, broadcast_period_ms=100, reply_latency_ms=0)
    )
    sent: list[int] = []
    t = 0.0
    while t <= 0.2 + 1e-9:
        sent += [i for i, _ in drive.poll(t)]
        t = drive.next_deadline()
    assert sent.count(ids.dp0_reply_id(1, 2)) == 20
    assert sent.count(ids.broadcast_id(1, 5, 6)) == 2
