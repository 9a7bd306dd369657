"""The simulated robot: where each drive's motors physically are, and how the robot moves.

The file's ``robots:`` section says which wheel each (unit, axis) turns and how it is
mounted; a robot wiring fault makes the machine differ from it, as a real one built wrong
does, while every drive still answers as the file expects (its encoder agrees with its
motor, so the per-motor checks pass):

- ``mirrored_wheel`` (unit, axis): that motor is mounted opposite to its wheel's ``sign``;
- ``swapped_drives`` (unit, other): each unit's drive sits on the other's wheels (axis A on
  A's, B on B's), as when the two drives' CAN or motor cables are crossed;
- ``swapped_axes_with_encoders`` (unit): motor A, with its encoder, turns the wheel the file
  gives axis B, and B turns A's;
- ``wrong_track`` (factor): the true track is ``factor`` × the file's;
- ``wrong_diameter`` (factor, unit or all): those wheels are ``factor`` × the file's diameter.

The robot integrates its true motion from the motors' true revolutions
(:attr:`SimDrive.revs`): each wheel's ground travel, the pose (x, y, heading) of a
differential base whose sides roll at the mean of their wheels (a skid-steer's wheels of
one side slip into agreement).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from abh3_supervisor.config.model import Fault, FaultKind
from abh3_supervisor.core.robot import RobotConfig, Side, Wheel
from abh3_supervisor.simulator.drive import SimDrive

Position = tuple[str, int]  # a wheel's place, named as the file names it: (unit, axis)


@dataclass(frozen=True, slots=True)
class PhysicalWheel:
    """A wheel as built: at ``place`` (the file's name of that wheel), turned by motor
    ``motor`` of the drive at ``address``, mounted with ``sign``, ``diameter_m`` across."""

    place: Wheel
    address: int
    motor: int
    sign: int
    diameter_m: float

    def ground(self, revs: float) -> float:
        """Metres rolled for ``revs`` motor revolutions."""
        return self.sign * revs * math.pi * self.diameter_m / self.place.gear_ratio


def _active(faults: Iterable[Fault], kind: FaultKind) -> list[Fault]:
    return [f for f in faults if f.kind is kind and f.active(0.0)]


def build(robot: RobotConfig, addresses: Mapping[str, int], faults: Iterable[Fault]) -> SimRobot:
    """The robot as built: the file's wheels, moved and turned by the faults."""
    faults = list(faults)
    drive_of = dict(addresses)  # unit → the address of the drive that sits on its wheels
    for f in _active(faults, FaultKind.SWAPPED_DRIVES):
        if f.unit in drive_of and f.other in drive_of:
            drive_of[f.unit], drive_of[f.other] = addresses[f.other], addresses[f.unit]
    swapped = {f.unit for f in _active(faults, FaultKind.SWAPPED_AXES_WITH_ENCODERS)}
    every = None in swapped
    mirrored = {(f.unit, f.axis) for f in _active(faults, FaultKind.MIRRORED_WHEEL)}
    wheels = []
    for w in robot.wheels:
        address = drive_of[w.unit]
        # the unit whose drive this is: a swap of its axes follows the drive, not the place
        owner = next(u for u, a in addresses.items() if a == address)
        motor = 1 - w.axis if every or owner in swapped else w.axis
        flip = (owner, motor) in mirrored or (None, motor) in mirrored
        diameter = w.diameter_m
        for f in _active(faults, FaultKind.WRONG_DIAMETER):
            if f.unit in (None, w.unit):
                diameter *= f.factor
        wheels.append(PhysicalWheel(w, address, motor, -w.sign if flip else w.sign, diameter))
    track = robot.track_m
    for f in _active(faults, FaultKind.WRONG_TRACK):
        track *= f.factor
    return SimRobot(robot.name, tuple(wheels), track)


class SimRobot:
    """A robot's true motion: per wheel place the metres rolled, and its pose."""

    def __init__(self, name: str, wheels: tuple[PhysicalWheel, ...], track_m: float) -> None:
        self.name, self.wheels, self.track_m = name, wheels, track_m
        self.x = self.y = self.heading = 0.0
        self.distance = 0.0  # the centre's path length [m]
        self.travel: dict[Position, float] = {(w.place.unit, w.place.axis): 0.0 for w in wheels}
        self._revs: dict[Position, float] | None = None

    def update(self, drives: Mapping[int, SimDrive]) -> None:
        """Integrate what the motors turned since the last update."""
        revs = {(w.place.unit, w.place.axis): drives[w.address].revs[w.motor] for w in self.wheels}
        before, self._revs = self._revs, revs
        if before is None:
            return
        step: dict[Side, list[float]] = {Side.LEFT: [], Side.RIGHT: []}
        for w in self.wheels:
            place = (w.place.unit, w.place.axis)
            d = w.ground(revs[place] - before[place])
            self.travel[place] += d
            step[w.place.side].append(d)
        left, right = (sum(v) / len(v) if v else 0.0 for v in step.values())
        turn = (right - left) / self.track_m
        ahead = (left + right) / 2
        mid = self.heading + turn / 2
        self.x += ahead * math.cos(mid)
        self.y += ahead * math.sin(mid)
        self.heading += turn
        self.distance += abs(ahead)

    def speeds(self, drives: Mapping[int, SimDrive]) -> dict[Position, float]:
        """Each wheel place's ground speed now [m/s], forward positive."""
        return {
            (w.place.unit, w.place.axis): w.ground(drives[w.address].vel[w.motor] / 60)
            for w in self.wheels
        }
