"""The robot decision under every sequence Hypothesis finds, on the fake clock.

A state machine drives a Supervisor (no bus, no simulator: the scheduler's events are
fed as a drive would cause them) through robots of several shapes and both generations:
switches, enables, twists, VELs, e-stops, replies, reboots of a drive (any length: the
drive comes back with its servo off, as after a power cut), gaps, offline spells, a
drive of the other generation. After every step the frames each unit would send — the
scheduler's payload, decoded here with the test's own bit tables — are judged against
what the fake drives really are, never against the supervisor's own state:

* **the robot**: a non-zero setpoint only while every drive of its robot is online,
  without a gap, of the declared generation, and has said (in a reply since our last
  change) SERVO and START on for every wheel axis;
* **no restart**: after a drive rebooted, no SERVO to it until the operator switched it
  on again;
* **identity**: a drive of the other generation (or one never heard) gets only the probe.
"""

from __future__ import annotations

import contextlib
import struct
from dataclasses import dataclass

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.readiness import SETTLE_S
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import frames
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.scheduler.core import (
    Event,
    FeedbackEvent,
    GapEvent,
    HealthEvent,
    StatusEvent,
)
from tests.support.rig import present, set_twist

# the test's own bit tables (protocol doc §5): SERVO and START per axis, per generation
SERVO = {"2021": (1 << 0, 1 << 12), "2023": (1 << 0, 1 << 8)}
START = {"2021": (1 << 1, 1 << 13), "2023": (1 << 1, 1 << 9)}
PROBE = 0x70

SHAPES = {
    "one drive (travel model)": """
units:
  - {name: a, abh3_id: 1}
""",
    "two drives, a wheel each": """
units:
  - {name: a, abh3_id: 1, velocity_model: motor}
  - {name: b, abh3_id: 3, protocol: "2023", velocity_model: motor}
robots:
  - {name: agv, track_m: 0.45, diameter_m: 0.2, gear_ratio: 20,
     wheels: [{unit: a, axis: A, side: left}, {unit: b, axis: A, side: right, sign: -1}]}
""",
    "skid-steer on two drives": """
units:
  - {name: a, abh3_id: 1, protocol: "2023", velocity_model: motor}
  - {name: b, abh3_id: 3, protocol: "2023", velocity_model: motor}
robots:
  - {name: skid, track_m: 0.6, diameter_m: 0.2, gear_ratio: 10,
     wheels: [{unit: a, axis: A, side: left}, {unit: a, axis: B, side: right},
              {unit: b, axis: A, side: left}, {unit: b, axis: B, side: right}]}
""",
}
HEAD = "buses:\n  b: {interface: virtual, channel: m}\n"


@dataclass
class FakeDrive:
    """What one drive really is: its generation, power, switches as it applies them."""

    generation: str
    declared: str
    wheels: tuple[int, ...]
    online: bool = True
    gap: bool = False
    applied: int = 0  # the SERVO/START bits it acts on (its own layout)
    reported: int = 0  # ``applied`` as its last reply said it
    tripped: bool = False  # an error holds its switches off until it is sent SERVO off
    rebooted: bool = False  # it lost its switches; the operator has not switched it on since
    said: float | None = None  # when it first replied since it lost them

    def need(self) -> int:
        return sum(SERVO[self.generation][a] | START[self.generation][a] for a in self.wheels)


class RobotDecision(RuleBasedStateMachine):
    @initialize(shape=st.sampled_from(sorted(SHAPES)), wrong=st.booleans())
    def build(self, shape: str, wrong: bool) -> None:
        self.now = 0.0
        self.config = parse_config(HEAD + SHAPES[shape], "m.yaml")
        self.sup = Supervisor(self.config, clock=lambda: self.now)
        self.scheduler = self.sup.schedulers["b"]
        self.names = list(self.config.units)
        robot = self.config.robot(self.names[0])
        assert robot is not None
        self.robot = robot.name
        self.owner = present(self.sup, self.names[0])
        self.drives: dict[str, FakeDrive] = {}
        for i, name in enumerate(self.names):
            declared = str(self.config.units[name].protocol)
            other = "2021" if declared == "2023" else "2023"
            generation = other if wrong and i == len(self.names) - 1 else declared
            self.drives[name] = FakeDrive(generation, declared, self.sup.units[name].wheels)
        self.last_sent: dict[str, bytes] = {}

    # ---------------------------------------------------------------- the drives

    def _frame(self, name: str) -> tuple[int, int, int]:
        ay, bx, word = struct.unpack("<hhI", self.scheduler.slots[name].payload)
        return ay, bx, word

    def _exchange(self, name: str) -> None:
        """Our frame reaches the drive, it acts on it and replies in its own layout."""
        drive = self.drives[name]
        if not drive.online or drive.gap:
            return
        sent_at = self.now
        word = self._frame(name)[2]
        gen = drive.generation
        both = sum(SERVO[gen]) | sum(START[gen])
        if drive.tripped and not word & sum(SERVO[gen]):
            drive.tripped = False  # SERVO off: the trip is reset
        drive.applied = 0 if drive.tripped else word & both
        drive.reported = drive.applied
        if gen == "2023":
            data = frames.encode_dp0_reply_2023(0, 0, drive.applied | word & PROBE)
        else:
            data = frames.encode_dp0_reply_2021(0, 0, 0, 0)
        self.now += 0.001
        reply = frames.decode_dp0_reply(data, self.config.units[name].protocol)
        events: list[Event] = [FeedbackEvent(name, self.now, reply, sent_at, data)]
        if gen == "2021" and drive.declared == "2021":  # its report: broadcast 1
            data1 = struct.pack("<II", drive.applied, 0)
            record = frames.decode_broadcast(1, data1, Generation.G2021)
            events.append(StatusEvent(name, self.now, 1, record, sent_at))
        self.scheduler.events.extend(events)
        self.sup.dispatch("b")
        if drive.said is None:
            drive.said = self.now

    @rule()
    def exchange_all(self) -> None:
        for name in self.names:
            self._exchange(name)
        self.now += 0.02

    @rule()
    def a_while(self) -> None:
        """Time passes at a slow command rate: the settle time after a change runs out."""
        for _ in range(6):
            for name in self.names:
                self._exchange(name)
            self.now += 0.1

    @rule(index=st.integers(0, 1))
    def exchange_one(self, index: int) -> None:
        self._exchange(self.names[index % len(self.names)])

    @rule(index=st.integers(0, 1))
    def trip(self, index: int) -> None:
        """An error: the drive switches itself off (no silence) and stays off until it is
        sent SERVO off — it is seen only in its replies."""
        drive = self.drives[self.names[index % len(self.names)]]
        if drive.applied & sum(SERVO[drive.generation]):
            drive.applied, drive.tripped, drive.rebooted, drive.said = 0, True, True, None

    @rule(index=st.integers(0, 1), seconds=st.sampled_from([0.6, 1.2, 5.0]))
    def reboot(self, index: int, seconds: float) -> None:
        """Power lost for ``seconds`` (a drive boots in about a second: never shorter than
        its command-zero timeout, so a gap): it comes back with its switches off, and
        offline first when the outage outlasts the timeout_ms."""
        name = self.names[index % len(self.names)]
        drive = self.drives[name]
        drive.applied, drive.rebooted, drive.said = 0, True, None
        self._event(GapEvent(name, self.now, True))
        drive.gap = True
        if seconds >= 1.2:
            self._event(HealthEvent(name, self.now, False))
            drive.online = False
        self.now += seconds
        if drive.online is False:
            self._event(HealthEvent(name, self.now, True))
            drive.online = True
        if drive.gap:
            self._event(GapEvent(name, self.now, False))
            drive.gap = False

    def _event(self, event: Event) -> None:
        self.scheduler.events.append(event)
        self.sup.dispatch("b")

    # ---------------------------------------------------------------- the operator

    def _operator_on(self, name: str) -> None:
        self.drives[name].rebooted = False  # an operator's act: switching on is allowed

    @rule(index=st.integers(0, 1), on=st.booleans())
    def switches(self, index: int, on: bool) -> None:
        name = self.names[index % len(self.names)]
        for text in ("SERVO", "START"):
            answer = self.sup.apply_text(name, f"{text} {'ON ON' if on else 'OFF OFF'}")
            if on and answer == "":
                self._operator_on(name)

    @rule(on=st.booleans())
    def enable(self, on: bool) -> None:
        try:
            self.sup.enable(self.robot, on)
        except CommandError:
            return
        if on:
            for name in self.names:
                self._operator_on(name)

    @rule(linear=st.sampled_from([0.0, 0.2, -0.3]), angular=st.sampled_from([0.0, 0.5]))
    def twist(self, linear: float, angular: float) -> None:
        with contextlib.suppress(CommandError):  # refused: said in its answer, judged below
            set_twist(self.sup, self.robot, linear, angular, source=self.owner)

    @rule(index=st.integers(0, 1), value=st.sampled_from([0, 150, -300]))
    def vel(self, index: int, value: int) -> None:
        self.sup.apply_text(self.names[index % len(self.names)], f"VEL {value} {value}")

    @rule(clear=st.booleans())
    def estop(self, clear: bool) -> None:
        if clear:
            self.sup.clear_emergency_stop()
        else:
            self.sup.emergency_stop()

    # ---------------------------------------------------------------- what must hold

    @invariant()
    def identity_before_energy(self) -> None:
        for name, drive in self.drives.items():
            if drive.generation != drive.declared:
                assert self._frame(name) == (0, 0, PROBE), (name, self._frame(name))

    @invariant()
    def no_restart(self) -> None:
        """Once a drive said it lost its switches, SERVO to it stops within the settle time
        (a switch just given may still be coming on) and stays off until the operator acts."""
        for name, drive in self.drives.items():
            if drive.rebooted and drive.said is not None and self.now - drive.said > SETTLE_S:
                servo = sum(SERVO[drive.declared])
                assert not self._frame(name)[2] & servo, f"{name}: SERVO after its reboot"

    @invariant()
    def the_robot_moves_whole_or_not_at_all(self) -> None:
        moving = [n for n in self.names if self._frame(n)[:2] != (0, 0)]
        if not moving:
            return
        for name, drive in self.drives.items():
            why = (
                "offline" if not drive.online
                else "in a gap" if drive.gap
                else "of the other generation" if drive.generation != drive.declared
                else "not reporting its wheels on" if drive.reported & drive.need() != drive.need()
                else None
            )  # fmt: skip
            assert why is None, f"{moving} commanded to move while {name} is {why}"


RobotDecision.TestCase.settings = settings(
    max_examples=5000,
    stateful_step_count=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
test_the_robot_decision_holds_under_every_sequence = RobotDecision.TestCase
