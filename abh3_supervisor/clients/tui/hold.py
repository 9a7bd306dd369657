"""A held arrow key, as far as a terminal tells: pure logic on an injected clock.

A terminal reports a key's press and its auto-repeats, not its release (Textual asks for
the kitty keyboard protocol without its event types, and xterm, tmux and ssh have none),
and the first auto-repeat comes only after the repeat delay (0.5–0.66 s: measured here
0.61 s, X11's default 660 ms) — longer than the service keeps a twist fresh (0.5 s). So
the TUI keeps the twist fresh itself while the key is held, re-sending it every
``RESEND_S``, and takes the key as released after a window without repeats: ``REPEAT_GAP_S``
once it repeats (repeats come every 33–100 ms), ``FIRST_REPEAT_S`` after a press (longer
than any default repeat delay). Then it sends zero at once. Silence still means zero: if
the TUI stops re-sending, the service zeroes the twist within its own 0.5 s.
"""

from __future__ import annotations

from dataclasses import dataclass

FIRST_REPEAT_S = 0.75  # after a press: longer than the terminal's repeat delay
REPEAT_GAP_S = 0.2  # once repeating: two or more missed repeats at the slowest rate
RESEND_S = 0.1  # the held twist again: well inside the service's 0.5 s freshness
TICK_S = 0.05  # how often the app looks: the release is said within this much more


@dataclass(frozen=True, slots=True)
class Drive:
    """One twist to some robots (each as a whole), as an arrow key asks it."""

    robots: tuple[str, ...]
    linear: float
    angular: float


class HeldKey:
    """The drive an arrow key holds, until the key is taken as released."""

    def __init__(self) -> None:
        self.drive: Drive | None = None
        self.key_at = float("-inf")  # the last press or repeat
        self._until = 0.0  # released when no repeat came by then
        self._sent_at = 0.0

    def press(self, drive: Drive, now: float) -> bool:
        """A press or an auto-repeat; True when ``drive`` is to be sent now (another key,
        another speed, nothing held), False when it keeps the held drive going."""
        repeating = drive == self.drive and now - self.key_at <= REPEAT_GAP_S
        self._until = now + (REPEAT_GAP_S if repeating else FIRST_REPEAT_S)
        self.key_at = now
        if drive == self.drive:
            return False
        self.drive, self._sent_at = drive, now
        return True

    def tick(self, now: float) -> tuple[Drive, bool] | None:
        """What to send at ``now``: ``(drive, True)`` the held drive again, ``(drive,
        False)`` zero to its robots (the key is up), or None: nothing."""
        drive = self.drive
        if drive is None:
            return None
        if now >= self._until:
            self.drive = None
            return drive, False
        if now - self._sent_at >= RESEND_S:
            self._sent_at = now
            return drive, True
        return None

    def stop(self) -> None:
        """Forget the held drive (space, the e-stop, a refusal): nothing more is sent."""
        self.drive = None
