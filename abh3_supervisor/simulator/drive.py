"""One simulated ABH3: command handling, drive-side timeouts, ramps, status values.

Modelled on the protocol doc: servo and start gating per axis, data select 0 written
(= set #7 & STOP) stops the axis, torque mode takes the command as a current, the
command-zero timeout raises alarm bit 22 and stops (START off), the error timeout raises
error bit 22, both clear when commands flow again (as §8 observed), other errors latch until
an error-reset rising edge ("0→1 resets, servo goes off", §5). An error turns the servo
off, and it stays off after the error is gone until the host's SERVO bit of the axis goes
off and on again — the drive never restarts a motor by itself.
Fault injection (``silent``, ``extra_delay``, ``inject_error``) is for tests and demos;
scripted faults (``faults``, from the YAML) switch the same behaviours on and off in time,
and wiring faults (a reversed or missing encoder, swapped motors, a pulse scale, the other
velocity model) make it the miswired drive a commissioning run must find.
Velocity follows the command on a ramp at ``accel``, or, given a time constant, as a
first-order lag (the current then also carries the acceleration).
Its parameter table (``tel.params``) says what it does: its address, group, timeouts and
periodic modes are written there, ``params`` overrides words (the file's view of the
drive, or a rehearsed mismatch: simulator/bus.py), and the timeouts are then taken from
the table (0x4117, 0x4118), as a real drive's are. Its address and host stay what the
frames use whatever 0x4102/0x4103 say, so a mismatch there can be read and reported.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Mapping

from abh3_supervisor.config.model import Fault, FaultKind, SimConfig, VelocityModel
from abh3_supervisor.core.kinematics import ab_to_yx, yx_to_ab
from abh3_supervisor.core.timing import next_on_grid
from abh3_supervisor.params import table
from abh3_supervisor.params.telabh3 import TelFormat
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.protocol.frames import Generation
from abh3_supervisor.protocol.ids import (
    ADDR_ALL,
    PF_REQUEST,
    PF_SINGLE,
    PF_TP_CM,
    PF_TP_DT,
    CanId,
    broadcast_id,
    dp0_reply_id,
)
from abh3_supervisor.protocol.scaling import ANALOG, CURRENT, LOAD, SUPPLY_VOLTAGE, VELOCITY
from abh3_supervisor.simulator.telabh3 import COMMAND_ZERO, ERROR_TIMEOUT, TelResponder, ms_of

PULSES_PER_REV = 4096  # when the file gives no geometry.pulses_per_rev
TORQUE_ACCEL_PER_PERCENT = 50.0  # min⁻¹/s per % of current command, torque mode
STALL_RATE = 400.0  # %/s: how fast the current rises on a motor without encoder feedback
STALL_MAX = 250.0  # % (the drive's current limit, roughly)
BOOT_S = 1.0  # power back on → first answer (a real drive takes about a second)


class SimDrive:
    def __init__(
        self,
        abh3_id: int,
        *,
        group: int = 5,
        generation: Generation = Generation.G2021,
        model: VelocityModel = VelocityModel.TRAVEL,
        cfg: SimConfig | None = None,
        now: float = 0.0,
        faults: tuple[Fault, ...] = (),
        params: Mapping[int, int] | None = None,
        accepts: tuple[TelFormat, ...] | None = None,
        pulses_per_rev: float = PULSES_PER_REV,
        time_constant_ms: float | None = None,
    ) -> None:
        self.abh3_id, self.group, self.generation = abh3_id, group, generation
        self.file_model = model  # what the file says; the drive may run the other one
        self.pulses_per_rev = pulses_per_rev
        self.tau = None if time_constant_ms is None else time_constant_ms / 1000
        self.layout = flags.layout(generation)  # a word of the other generation misleads it
        self.cfg = cfg or SimConfig()
        zero_ms = self.cfg.command_zero_timeout_ms  # None: a drive on its own, the seed's 500
        self.command_zero_ms: int = 500 if zero_ms is None else zero_ms
        self.error_timeout_ms = self.cfg.error_timeout_ms
        self.inputs = 0
        self.cmd_raw = (0, 0)  # last AY/BX command as written
        self.vel = [0.0, 0.0]  # motor A, B [min⁻¹], as they turn
        self.pulses = [0.0, 0.0]
        self.revs = [0.0, 0.0]  # motor revolutions truly turned, whatever the encoder says
        self.accel_now = [0.0, 0.0]  # min⁻¹/s, first-order mode only (it costs current)
        self.stall = [0.0, 0.0]  # % of current pushed into a motor whose encoder is silent
        self.errors = 0  # latched errors (bit 22 is derived from the timeouts)
        self.alarms = 0
        # per axis: the servo went off for an error (or an error reset) while its SERVO
        # input was on; it stays off until the host turns that input off (then on again)
        self.servo_tripped = [False, False]
        self.last_command: float | None = None
        self.t = now
        self.started = now  # scripted faults count from here
        self.booted = now  # the drive's own timeouts count from here until a command
        # power and the CAN cable (`abh3 simulate`'s commands): without either the drive
        # neither hears nor is heard; without power its motors run down, servo off
        self.powered = True
        self.plugged = True
        self.awake_at = now  # powered again: answers from here (it boots)
        self.host = 2  # where periodic frames go until a host speaks
        # fault injection
        self.silent = False
        self.extra_delay = 0.0
        self.faults = tuple(f for f in faults if f.kind is not FaultKind.BUS_SEND_ERROR)
        self._out: list[tuple[float, int, int, bytes]] = []
        self._seq = itertools.count()
        self._next_dp0 = now + self.cfg.dp0_period_ms / 1000 if self.cfg.dp0_period_ms else math.inf
        bp = self.cfg.broadcast_period_ms
        self._next_brd = now + bp / 1000 if bp else math.inf
        self.frames_received = 0
        self.tel = TelResponder(abh3_id, self, self._fault_value, accepts)
        self.tel.params.update(self._set_up())
        self.tel.params.update(params or {})
        self._stored = dict(self.tel.params)  # what a power cycle reloads
        self._timeouts_from_table()

    def _timeouts_from_table(self) -> None:
        self.command_zero_ms = ms_of(self.tel.params[COMMAND_ZERO])
        self.error_timeout_ms = ms_of(self.tel.params[ERROR_TIMEOUT])

    def _set_up(self) -> dict[int, int]:
        """The words of the parameters this drive acts on or is: what the table says."""
        words = {
            0x4102: self.abh3_id,
            0x4105: self.cfg.dp0_period_ms,  # 0: a reply on receipt (or request)
            0x4107: self.group,
            COMMAND_ZERO: self.command_zero_ms,
            ERROR_TIMEOUT: self.error_timeout_ms,
        }
        words.update({0x4108 + n: self.cfg.broadcast_period_ms for n in range(7)})
        return {a: table.to_word(v, table.kind_of(a)) for a, v in words.items()}

    # ------------------------------------------------------------ fault injection

    def inject_error(self, bits: int) -> None:
        self.errors |= bits
        self._trip()

    def inject_alarm(self, bits: int) -> None:
        self.alarms |= bits

    # ------------------------------------------------------------ power and cable

    def power_off(self, now: float) -> None:
        """Its power cut: it hears and sends nothing, its servo drops, its motors run
        down (at its ramp, braked), and whatever it was doing is gone."""
        self.advance(now)
        self.powered = False
        self.inputs, self.cmd_raw = 0, (0, 0)
        self._out.clear()

    def power_on(self, now: float, *, keep_writes: bool = False) -> None:
        """Power back: it boots for ``BOOT_S`` (silent), then answers as a drive just
        switched on — servo and start off, no command heard (the command-zero timeout's
        alarm stands until one comes), counters at zero, errors cleared, its parameter
        table reloaded: as set up, or ``keep_writes`` with what was written meanwhile
        (whether an ABH3 keeps parameters written over CAN is in no public source)."""
        self.advance(now)
        if self.powered:
            return
        self.powered = True
        self.awake_at = now + BOOT_S
        self.booted = self.awake_at
        self.last_command = None
        self.pulses, self.errors, self.alarms = [0.0, 0.0], 0, 0
        self.servo_tripped = [False, False]
        self.vel = [0.0, 0.0]  # it ran down while off
        if not keep_writes:
            self.tel.params.clear()
            self.tel.params.update(self._stored)
        self._timeouts_from_table()

    def hears(self, now: float) -> bool:
        """Whether a frame on the bus reaches it now (powered, booted, cable in)."""
        return self.powered and self.plugged and now >= self.awake_at

    # ------------------------------------------------------------ bus side

    def on_frame(self, arbitration_id: int, data: bytes, now: float) -> None:
        if not self.hears(now) or arbitration_id >> 24 & 1:  # data page 1: no PGN of its
            return
        cid = CanId.from_int(arbitration_id)
        if cid.pf == PF_SINGLE and cid.ps == self.abh3_id and len(data) == 8:
            self.advance(now)
            self.frames_received += 1
            self.host = cid.sa
            self._apply_command(data, now)
            self._queue(now, dp0_reply_id(self.abh3_id, cid.sa), self._dp0_reply())
        elif cid.pf in (PF_TP_CM, PF_TP_DT) and cid.ps == self.abh3_id and data:
            self.advance(now)
            self.tel.on_frame(cid.sa, cid.pf == PF_TP_DT, data, now)
            for frame in self.tel.poll(now):
                self._queue(now, *frame)
        elif cid.pf == PF_REQUEST and cid.ps in (self.abh3_id, ADDR_ALL) and len(data) >= 3:
            self.advance(now)
            self.frames_received += 1
            request = frames.decode_request(data)
            if not isinstance(request, frames.Request):
                return
            if request.is_dp0:
                self._queue(now, dp0_reply_id(self.abh3_id, cid.sa), self._dp0_reply())
            elif (target := request.broadcast) is not None and target[0] == self.group:
                self._queue(
                    now,
                    broadcast_id(self.abh3_id, self.group, target[1]),
                    self.broadcast(target[1]),
                )

    def _fault(self, kind: FaultKind, now: float) -> Fault | None:
        for fault in self.faults:
            if fault.kind is kind and fault.active(now - self.started):
                return fault
        return None

    def _fault_value(self, kind: FaultKind, now: float) -> float | None:
        """For the parameter side: None, or the active fault's ``delay_ms``."""
        fault = self._fault(kind, now)
        return None if fault is None else fault.delay_ms

    @property
    def model(self) -> VelocityModel:
        """The velocity model the drive runs: the file's, unless set up otherwise."""
        if not self._fault(FaultKind.OTHER_VELOCITY_MODEL, self.t):
            return self.file_model
        travel = self.file_model is VelocityModel.TRAVEL
        return VelocityModel.MOTOR if travel else VelocityModel.TRAVEL

    def _axis_fault(self, kind: FaultKind, axis: int) -> Fault | None:
        for fault in self.faults:
            if fault.kind is kind and fault.axis == axis and fault.active(self.t - self.started):
                return fault
        return None

    def sensed(self, axis: int) -> float:
        """Motor ``axis``'s velocity as its encoder tells the drive (and the drive tells us)."""
        if self._axis_fault(FaultKind.NO_ENCODER, axis):
            return 0.0
        reversed_ = self._axis_fault(FaultKind.REVERSED_AXIS, axis) is not None
        return -self.vel[axis] if reversed_ else self.vel[axis]

    def _queue(self, now: float, arbitration_id: int, data: bytes) -> None:
        if self.silent or not self.hears(now) or self._fault(FaultKind.SILENT, now):
            return
        if self._fault(FaultKind.MALFORMED_REPLIES, now):
            data = b""
        slow = self._fault(FaultKind.SLOW_REPLIES, now)
        delay = self.extra_delay + (slow.delay_ms / 1000 if slow else 0.0)
        due = now + self.cfg.reply_latency_ms / 1000 + delay
        heapq.heappush(self._out, (due, next(self._seq), arbitration_id, data))

    def poll(self, now: float) -> list[tuple[int, bytes]]:
        self.advance(now)
        if now >= self._next_dp0:
            self._next_dp0 = next_on_grid(self._next_dp0, self.cfg.dp0_period_ms / 1000, now)
            self._queue(now, dp0_reply_id(self.abh3_id, self.host), self._dp0_reply())
        if now >= self._next_brd:
            self._next_brd = next_on_grid(self._next_brd, self.cfg.broadcast_period_ms / 1000, now)
            for n in range(7):
                self._queue(now, broadcast_id(self.abh3_id, self.group, n), self.broadcast(n))
        for frame in self.tel.poll(now):
            self._queue(now, *frame)
        out = []
        while self._out and self._out[0][0] <= now:
            _, _, arbitration_id, data = heapq.heappop(self._out)
            out.append((arbitration_id, data))
        return out

    def next_deadline(self) -> float:
        due = self._out[0][0] if self._out else math.inf
        return min(
            due,
            self._next_dp0,
            self._next_brd,
            self._timeout_deadline(),
            self._error_fault_start(),
            self.tel.next_deadline(),
        )

    def _error_fault_start(self) -> float:
        # wake up when scripted error bits appear, so the servo trips even between frames
        starts = (self._since(f.at_s) for f in self.faults if f.kind is FaultKind.ERROR_BITS)
        return min((t for t in starts if t > self.t), default=math.inf)

    def _since(self, seconds: float) -> float:
        """The first time at which ``_fault`` counts ``seconds`` as passed since the start
        (``started + seconds`` may round below it: then waking there would see nothing)."""
        t = self.started + seconds
        while t - self.started < seconds:
            t = math.nextafter(t, math.inf)
        return t

    def _timeout_deadline(self) -> float:
        # wake up when a drive-side timeout is about to fire, so bit 22 appears on time
        last = self.last_command if self.last_command is not None else self.booted
        deadline = math.inf
        for ms in (self.command_zero_ms, self.error_timeout_ms):
            if ms and self.t < last + ms / 1000 < deadline:
                deadline = last + ms / 1000
        return deadline

    # ------------------------------------------------------------ drive behaviour

    def _apply_command(self, data: bytes, now: float) -> None:
        ay, bx, inputs = frames.unpack_dp0_command(data)
        lay = self.layout
        rising = inputs & ~self.inputs
        for axis in (0, 1):
            if rising & lay.pulse_clear.of(axis):
                self.pulses[axis] = 0.0
        self.inputs, self.cmd_raw, self.last_command = inputs, (ay, bx), now
        if rising & lay.error_reset:
            self.errors = 0
            self.servo_tripped = [True, True]  # the servo goes off (kept only where SERVO is on)
        self._trip()

    def _trip(self) -> None:
        """An error present trips the servo of each axis whose SERVO input is on; a SERVO
        input seen off re-arms its axis. So after an error clears the servo stays off until
        the host cycles SERVO (off, then on), as a real drive's does."""
        error = bool(self.error_word())
        for axis in (0, 1):
            if not self.inputs & self.layout.servo.of(axis):
                self.servo_tripped[axis] = False
            elif error:
                self.servo_tripped[axis] = True

    def _silence(self, timeout_ms: int) -> bool:
        if not timeout_ms:
            return False
        last = self.last_command if self.last_command is not None else self.booted
        # the same sum as in _timeout_deadline, so waking at it always sees the timeout
        return self.t >= last + timeout_ms / 1000 or self.last_command is None

    def command_zero_fired(self) -> bool:
        """Commanded once, then silent for its command-zero timeout: it stopped itself."""
        return self.last_command is not None and self._silence(self.command_zero_ms)

    def error_word(self) -> int:
        scripted = self._fault(FaultKind.ERROR_BITS, self.t)
        return (
            self.errors
            | (scripted.bits if scripted else 0)
            | (flags.CAN_COMM_ERROR if self._silence(self.error_timeout_ms) else 0)
        )

    def alarm_word(self) -> int:
        cz = self._silence(self.command_zero_ms)
        return self.alarms | (flags.CAN_COMM_ERROR if cz else 0)

    def _servo(self, axis: int) -> bool:
        bit = self.layout.servo.of(axis)
        return bool(self.inputs & bit) and not self.error_word() and not self.servo_tripped[axis]

    def _started(self, axis: int) -> bool:
        cz = self._silence(self.command_zero_ms)
        return self._servo(axis) and bool(self.inputs & self.layout.start.of(axis)) and not cz

    def _brake_released(self) -> bool:
        return self._servo(0) or bool(self.inputs & self.layout.brake_release)

    def control_word(self) -> int:
        """The input bits the drive acts on (SERVO/START as they are in effect), plus the
        model bit; in 2023 also ready, busy, brake output and error (bits 25–31)."""
        lay = self.layout
        word = self.inputs & lay.input.defined & ~(lay.servo.both | lay.start.both)
        for axis in (0, 1):
            if self._servo(axis):
                word |= lay.servo.of(axis) | lay.ready.of(axis)
                word |= lay.busy.of(axis) if self._axis_target(axis)[0] != 0.0 else 0
            word |= lay.start.of(axis) if self._started(axis) else 0
        if self.generation is Generation.G2023:
            word |= lay.control.mask("BRAKE_RELEASE_OUT") if self._brake_released() else 0
            word |= lay.control.mask("ERROR") if self.error_word() else 0
        return word | (lay.travel_model if self.model is VelocityModel.TRAVEL else 0)

    def _axis_target(self, axis: int) -> tuple[float, bool]:
        """(command for this command axis, is_current) after gating and polarity."""
        raw = self.cmd_raw[axis]
        torque = bool(self.inputs & self.layout.torque.of(axis))
        select = self.layout.data_select(self.inputs)[axis]
        if not self._started(axis) or select == 0:  # written 0 = set #7 & STOP
            return 0.0, torque
        value = (CURRENT if torque else VELOCITY).to_physical(raw)
        return (-value if self.inputs & self.layout.reverse.of(axis) else value), torque

    def advance(self, now: float) -> None:
        dt = now - self.t
        if dt <= 0:
            return
        self.t = now
        self._trip()  # an error that came on meanwhile (a timeout, a scripted fault)
        (t0, torque0), (t1, torque1) = self._axis_target(0), self._axis_target(1)
        travel = self.model is VelocityModel.TRAVEL
        targets = yx_to_ab(t0, t1) if travel else (t0, t1)
        torque = (torque0, torque1)
        servo = [
            self._servo(i) if not travel else (self._servo(0) and self._servo(1)) for i in (0, 1)
        ]
        order = (1, 0) if self._fault(FaultKind.SWAPPED_AXES, now) else (0, 1)
        for i, source in enumerate(order):  # swapped: A's command reaches motor B's windings
            goal = targets[source] if servo[source] else 0.0
            before = self.vel[i]
            if self._axis_fault(FaultKind.NO_ENCODER, i):
                self._stalled(i, goal, dt)
                continue
            if torque[source] and servo[source]:
                self.vel[i] += targets[source] * TORQUE_ACCEL_PER_PERCENT * dt
            elif self.tau is not None:
                self.vel[i] = goal + (self.vel[i] - goal) * math.exp(-dt / self.tau)
            else:
                step = self.cfg.accel * dt
                self.vel[i] += max(-step, min(step, goal - self.vel[i]))
            self.vel[i] = max(VELOCITY.minimum, min(VELOCITY.maximum, self.vel[i]))
            self.accel_now[i] = (self.vel[i] - before) / dt if self.tau is not None else 0.0
            self.revs[i] += self.vel[i] / 60 * dt
            scale = self._axis_fault(FaultKind.SCALE, i)
            counts = self.sensed(i) * (scale.factor if scale else 1.0)
            self.pulses[i] += counts / 60 * self.pulses_per_rev * dt

    def _stalled(self, axis: int, goal: float, dt: float) -> None:
        """No encoder: the drive sees the motor standing and pushes current, up to its
        limit, while a command asks for motion; nothing turns, nothing is counted."""
        self.vel[axis], self.accel_now[axis] = 0.0, 0.0
        rise = STALL_RATE * dt * (1 if goal else -2)
        magnitude = max(0.0, min(STALL_MAX, abs(self.stall[axis]) + rise))
        sign = math.copysign(1.0, goal) if goal else math.copysign(1.0, self.stall[axis])
        self.stall[axis] = sign * magnitude

    # ------------------------------------------------------------ parameter side

    def set_command_zero_ms(self, ms: int) -> None:
        """Parameter 0x4117 written: the drive's command-zero timeout from now on."""
        self.command_zero_ms = ms

    def set_error_timeout_ms(self, ms: int) -> None:
        """Parameter 0x4118 written: the drive's CAN error timeout from now on."""
        self.error_timeout_ms = ms

    def monitor(self, address: int) -> float | None:
        """A ``CM`` monitor (§1.4) from the simulated state; None: no such monitor."""
        ay, bx = self._ay_bx()
        values: dict[int, float] = {
            0x0000: self.error_word(),
            0x0001: self.alarm_word(),
            0x0002: self.inputs,
            0x0003: self.control_word(),
            0x0004: 0,
            0x0005: 0,
            0x1004: 23.7,
            0x1005: 23.7,
            0x1012: ay,
            0x1022: bx,
            0x1031: self.current(0),
            0x1041: self.current(1),
            0x103B: self.load(0),
            0x104B: self.load(1),
            0x1054: self.pulse_count(0),
            0x1064: self.pulse_count(1),
        }
        return values.get(address)

    def pulse_count(self, axis: int) -> int:
        """The encoder count as the drive reports it: int32, wrapping."""
        return ((int(self.pulses[axis]) + 2**31) % 2**32) - 2**31

    # ------------------------------------------------------------ frames out

    def _ay_bx(self) -> tuple[float, float]:
        a, b = self.sensed(0), self.sensed(1)
        return ab_to_yx(a, b) if self.model is VelocityModel.TRAVEL else (a, b)

    def _dp0_reply(self) -> bytes:
        r = VELOCITY.to_raw
        if self.generation is Generation.G2023:
            ay, bx = self._ay_bx()
            return frames.encode_dp0_reply_2023(r(ay)[0], r(bx)[0], self.control_word())
        a, b = self.sensed(0), self.sensed(1)
        y, x = ab_to_yx(a, b)
        return frames.encode_dp0_reply_2021(r(a)[0], r(b)[0], r(y)[0], r(x)[0])

    def load(self, axis: int) -> float:
        return min(255.0, 3.0 + abs(self.vel[axis]) / 40 + abs(self.stall[axis]))

    def current(self, axis: int) -> float:
        """Signed current [%]: what holds the speed, what accelerates, what a stall pushes."""
        if self.stall[axis]:
            return math.copysign(self.load(axis), self.stall[axis])
        holding = math.copysign(self.load(axis), self.vel[axis])
        return holding + self.accel_now[axis] / TORQUE_ACCEL_PER_PERCENT

    def io_word(self) -> int:
        """2021: status bits; 2023: the wired digital I/O, of which the simulator has none."""
        if self.generation is Generation.G2023:
            return 0
        io = self.layout.io
        word = (io.mask("ERROR") if self.error_word() else 0) | (
            io.mask("ALARM") if self.alarm_word() else 0
        )
        for axis, (ready, busy) in enumerate((("AY_READY", "AY_BUSY"), ("BX_READY", "BX_BUSY"))):
            if self._servo(axis):
                word |= io.mask(ready)
                if self._axis_target(axis)[0] != 0.0:
                    word |= io.mask(busy)
        if self._brake_released():
            word |= io.mask("BRAKE_RELEASED")
        return word

    def broadcast(self, n: int) -> bytes:
        v, c = VELOCITY.to_raw, CURRENT.to_raw
        if n == 0:
            return frames.encode_words(self.error_word(), self.alarm_word())
        if n == 1:
            if self.generation is Generation.G2023:  # the input word as the drive sees it
                return frames.encode_words(self.io_word(), self.inputs & self.layout.input.defined)
            return frames.encode_words(self.control_word(), self.io_word())
        if n == 2:
            cmd = [self._axis_target(i)[0] for i in range(2)]
            fbk = self._ay_bx()
            return frames.encode_int16x4(v(cmd[0])[0], v(cmd[1])[0], v(fbk[0])[0], v(fbk[1])[0])
        if n == 3:
            loads = [LOAD.to_raw(self.load(i))[0] for i in range(2)]
            cur = [c(self.current(i))[0] for i in range(2)]
            return frames.encode_int16x2_uint16x2(cur[0], cur[1], loads[0], loads[1])
        if n == 4:
            return frames.encode_pulses(self.pulse_count(0), self.pulse_count(1))
        if n == 5:
            sag = (self.load(0) + self.load(1)) / 200  # main supply sags a little under load
            return frames.encode_int16x2_uint16x2(
                ANALOG.to_raw(0.21)[0],
                ANALOG.to_raw(0.14)[0],
                SUPPLY_VOLTAGE.to_raw(23.7 - sag)[0],
                SUPPLY_VOLTAGE.to_raw(23.7)[0],
            )
        if n == 6:
            return frames.encode_monitors(self.sensed(0) / 1000, self.sensed(1) / 1000)
        return bytes(8)
