"""Safety is the frame: while a unit moves for commissioning, every DP0 answer is checked
the moment it arrives (a supervisor observer, on the loop), and the first unexpected one
stops the unit at once — feedback against the command, speed beyond 2× the asked jog, no
feedback, the other motor moving, an error bit. An answer that does not come is a fault
too: the sequence asks :meth:`Guard.tick` at :meth:`Guard.deadline` at the latest, so a
drive gone silent is stopped ``SILENCE_S`` after its last answer, and no jog or reversal
is commanded after that."""

from __future__ import annotations

import math
from collections.abc import Callable

from abh3_supervisor.commission.analysis import FOLLOWS, OTHER_MOVES, OVERSPEED, SILENCE_S
from abh3_supervisor.commission.model import AXES
from abh3_supervisor.core.supervisor import Supervisor, SupervisorEvent
from abh3_supervisor.protocol import flags, frames
from abh3_supervisor.scheduler.core import FeedbackEvent, StatusEvent


class Guard:
    """Watches ``unit``; ``stop(reason)`` is called once, on the first unexpected answer.

    ``ceiling`` is the largest speed the run asks for: nothing may ever turn faster than
    twice that. :meth:`expect` announces each new command (motor, speed, when)."""

    def __init__(
        self, sup: Supervisor, unit: str, ceiling: float, stop: Callable[[str], None]
    ) -> None:
        self.sup, self.unit, self.ceiling, self._stop = sup, unit, ceiling, stop
        self.tripped: str | None = None
        self.silence: float | None = None  # tripped by a drive gone silent: for how long
        self.axis, self.speed, self.since, self.grace = 0, 0.0, 0.0, math.inf
        self._from_rest = True
        fb = sup.units[unit].feedback
        self.heard = fb.t if fb is not None else sup.clock()  # the drive's last DP0 answer

    def expect(self, axis: int, speed: float, now: float, grace: float) -> None:
        """Motor ``axis`` is asked for ``speed`` from ``now``; it must follow within
        ``grace`` seconds (before that, a motor still turning the other way is allowed)."""
        fb = self.sup.units[self.unit].feedback
        current = (fb.vel_a, fb.vel_b)[axis] if fb is not None else 0.0
        self._from_rest = abs(current) < FOLLOWS * max(abs(speed), 1e-9)
        self.axis, self.speed, self.since, self.grace = axis, speed, now, grace

    def __call__(self, event: SupervisorEvent) -> None:
        if getattr(event, "unit", None) != self.unit:
            return
        if isinstance(event, FeedbackEvent) and not isinstance(event.reply, frames.Unknown):
            self.heard = max(self.heard, event.t)
        if self.tripped is None and isinstance(event, StatusEvent | FeedbackEvent):
            reason = self.judge(event.t)
            if reason is not None:
                self._trip(reason)

    def deadline(self) -> float:
        """When the drive's silence becomes a fault unless it answers before."""
        return self.heard + SILENCE_S

    def tick(self, now: float) -> None:
        """The time is ``now``: a drive silent since :meth:`deadline` stops the unit."""
        if self.tripped is None and now >= self.deadline():
            self.silence = now - self.heard
            self._trip(f"no answer from the drive for {self.silence:.2f} s: communication lost")

    def _trip(self, reason: str) -> None:
        self.tripped = reason
        self._stop(reason)

    def judge(self, now: float) -> str | None:
        state = self.sup.units[self.unit]
        error = state.words.get("error", 0)
        if error:
            return f"error bit: {', '.join(flags.FAULT.labels(error))}"
        fb = state.feedback
        if fb is None:
            return None
        motors = (fb.vel_a, fb.vel_b)
        for name, value in zip(AXES, motors, strict=True):
            if abs(value) > OVERSPEED * self.ceiling:
                return f"motor {name} at {value:+.1f} min⁻¹, beyond 2× the jog ({self.ceiling:g})"
        v = self.speed
        if v == 0:
            return None
        asked, other = motors[self.axis], motors[1 - self.axis]
        name, other_name = AXES[self.axis], AXES[1 - self.axis]
        late = now - self.since > self.grace
        if abs(other) > OTHER_MOVES * abs(v):
            return f"motor {other_name} moves ({other:+.1f} min⁻¹) when {name} was asked ({v:+g})"
        if asked * math.copysign(1.0, v) < -FOLLOWS * abs(v) and (self._from_rest or late):
            return f"motor {name}'s feedback {asked:+.1f} min⁻¹ is against the command {v:+g}"
        if late and abs(asked) < FOLLOWS * abs(v):
            return f"no feedback from motor {name} ({asked:+.1f} min⁻¹ for {v:+g})"
        return None
