"""One owner of the terminal's keys.

Two readers of one terminal lose keys to each other at random (an e-stop among them), so
a front end that owns the terminal (the TUI) claims it before any input source starts.
An input source that reads keys from the terminal checks :func:`owner` in ``start`` and,
when the terminal is taken, leaves it alone and implements :class:`KeyInput` instead:
the owner hands it the keys it does not use itself.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Protocol, runtime_checkable

_owner: str | None = None


def claim(owner: str) -> None:
    global _owner
    _owner = owner


def release() -> None:
    global _owner
    _owner = None


def owner() -> str | None:
    """Who reads the terminal's keys (e.g. ``"the TUI"``), or None: nobody yet."""
    return _owner


@runtime_checkable
class KeyInput(Protocol):
    """An input source the terminal's owner hands keys to (from the owner's thread)."""

    def key_map(self, taken: Collection[str]) -> dict[str, str]:
        """The keys (single characters) this source wants, avoiding ``taken`` (the
        owner's own), each with what it does; the owner documents them in its help."""
        ...

    def press(self, key: str) -> None:
        """A key of :meth:`key_map` was typed."""
        ...
