"""Whether a robot may move, from what each of its drives reports: a pure decision.

A robot moves whole or not at all. Its setpoints reach the wire only while every drive of
it is *ready*: heard and online, exchanging without a gap, recognised as the generation
the file declares, commanded SERVO and START on every axis that drives a wheel, and
reporting exactly that — in an answer to a frame sent after the last change of those
switches — with no error. :func:`drive_unready` says why one drive is not;
:func:`robot_unready` why a robot is not (the first drive that is not, by name).

A reason is *pending* while it is expected to resolve by itself within one exchange or a
short settle time after the operator's own act (the drive not heard yet, not identified
yet, not yet reporting a change just commanded): a request given then is taken and held
at zero on the wire until the drive reports ready. Every other reason is a *fault*: the
request is refused in its answer, naming the drive and why, and when a ready robot meets
one, every drive of it gets zero in its next frame and what it was asked is consumed —
only a command given after the recovery moves it again (docs/safety.md, "The robot
decision").

Nothing here reads a clock or touches state: the Supervisor builds a :class:`DriveView`
per drive from what it was told, and applies the answer.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from abh3_supervisor.protocol import flags
from abh3_supervisor.protocol.generation import Generation

AXES = ("A", "B")
# how long a drive may take to report a switch it was just given before it is taken as
# not following (a real drive's servo needs a few ms to tens of ms to come on)
SETTLE_S = 0.5


@dataclass(frozen=True, slots=True)
class Unready:
    """Why a drive (or a robot) may not move; ``pending``: it may resolve by itself."""

    why: str
    pending: bool = False


@dataclass(frozen=True, slots=True)
class DriveView:
    """The explicit conditions one drive is decided from.

    ``wheels``: the axes (0 = A, 1 = B) that drive a wheel of its robot; ``commanded``:
    the input word this supervisor commands; ``reported``: the drive's control word from
    the latest report answering a frame sent after the last change of the wheel axes'
    SERVO/START (None: none yet); ``error``: that report says an error is present.
    """

    name: str
    layout: flags.Layout
    declared: Generation
    wheels: tuple[int, ...]
    online: bool | None
    gap: bool
    identified: Generation | None  # the generation its replies show; None: not yet
    commanded: int
    reported: int | None
    error: bool = False

    @property
    def need(self) -> int:
        """SERVO and START of every wheel axis: the bits a ready drive reports on."""
        return switches(self.layout, self.wheels)


def switches(layout: flags.Layout, axes: Iterable[int]) -> int:
    """SERVO and START of ``axes`` (0 = A/Y, 1 = B/X) in ``layout``."""
    return sum(layout.servo.of(a) | layout.start.of(a) for a in axes)


def switch_names(layout: flags.Layout, bits: int) -> str:
    """The switches of ``bits`` by name, e.g. ``SERVO A, START B``."""
    names = []
    for switch, pair in (("SERVO", layout.servo), ("START", layout.start)):
        names += [f"{switch} {AXES[a]}" for a in (0, 1) if bits & pair.of(a)]
    return ", ".join(names)


def drive_unready(view: DriveView) -> Unready | None:
    """Why this drive may not move its robot now, or None when it is ready."""
    if view.online is None:
        return Unready("not heard yet", pending=True)
    if not view.online:
        return Unready("offline (no answer within its timeout_ms)")
    if view.gap:
        return Unready("no exchange for its drive_timeout_ms (it stopped itself)")
    if view.identified is None:
        return Unready(f"not yet recognised as a {view.declared} drive", pending=True)
    if view.identified is not view.declared:
        return Unready(
            f"answers as a {view.identified} drive, the file says protocol: "
            f'"{view.declared}" (held at a word safe in both generations)'
        )
    missing = view.need & ~view.commanded
    if missing:
        return Unready(f"{switch_names(view.layout, missing)} not switched on")
    if view.reported is None:
        return Unready("has not yet reported the switches it was given", pending=True)
    if view.error:
        return Unready("reports an error: reset it (RESET), then SERVO and START again")
    absent = view.need & ~view.reported
    if absent:
        return Unready(f"reports {switch_names(view.layout, absent)} off", pending=True)
    return None


def robot_unready(views: Iterable[DriveView]) -> Unready | None:
    """Why the robot of these drives may not move: its first drive that may not (a fault
    before a pending reason, so a refusal names what will not resolve by itself)."""
    first: Unready | None = None
    for view in views:
        why = drive_unready(view)
        if why is None:
            continue
        named = Unready(f"{view.name}: {why.why}", why.pending)
        if not why.pending:
            return named
        first = first or named
    return first


def reply_generation(data: bytes, probed: bool) -> Generation | None:
    """The generation one DP0 reply's 8 bytes show, or None when they could be either.

    A 2021 reply is four velocities, Y and X following from A and B (doc §7); a 2023 reply
    is two velocities and the control word. Bytes that are not a consistent 2021 reply are
    2023's. A reply of all zeros reads alike in both — unless it answers a frame carrying
    :data:`flags.ID_PROBE` (``probed``): a 2023 drive reports the data select it is given
    in its control word, so an all-zero answer to it is a 2021 drive's (docs/safety.md,
    "Identity before energy", says what this assumes).
    """
    a = int.from_bytes(data[0:2], "little", signed=True)
    b = int.from_bytes(data[2:4], "little", signed=True)
    y = int.from_bytes(data[4:6], "little", signed=True)
    x = int.from_bytes(data[6:8], "little", signed=True)
    if abs(2 * y - (a + b)) > 2 or abs(x - (a - y)) > 2:
        return Generation.G2023
    if a or b or y or x:
        return Generation.G2021
    return Generation.G2021 if probed else None


__all__ = [
    "SETTLE_S",
    "DriveView",
    "Unready",
    "drive_unready",
    "reply_generation",
    "robot_unready",
    "switch_names",
    "switches",
]
