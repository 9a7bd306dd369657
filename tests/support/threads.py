"""Races made to show: threads switch as often as the interpreter allows."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def switching_often() -> Iterator[None]:
    """A thread switch almost anywhere (every microsecond) while inside."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        yield
    finally:
        sys.setswitchinterval(before)
