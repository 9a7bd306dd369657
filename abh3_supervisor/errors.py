"""One exception root; each subclass is a phase a user can act on. And the two hints
many messages end with: the name the user probably meant, how to install an extra."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class Abh3Error(Exception):
    """Root of every error this package raises on purpose."""


class CodecError(Abh3Error, ValueError):
    """A value cannot be put on the wire (NaN, infinity, wrong type)."""


class ConfigError(Abh3Error):
    """The YAML configuration is invalid; ``problems`` holds one line per fault."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("\n".join(problems))
        self.problems = problems


class CommandError(Abh3Error):
    """A supervisor command was refused (unknown unit, wrong mode, e-stop latched)."""


class BusInUse(Abh3Error):
    """Another host already commands a drive this tool would touch (core/foreign.py):
    exit 2, before anything is sent."""


class RunError(Abh3Error):
    """What only the run itself can find out failed (a device, an output, a plugin's start):
    exit 1, and before any drive is commanded where it is found at start-up."""


class BusOpenError(RunError):
    """A CAN bus could not be opened (missing device, interface not installed)."""


class PartialWrite(RunError):
    """Some parameters were written and then the run stopped (failure or signal): exit 4,
    with the journal that undoes them saved."""


class PluginError(RunError):
    """A plugin could not start (or blocked starting)."""


class Interrupted(BaseException):
    """A stop signal before the runtime took over signals (or in a one-shot client), or
    after it gave them back.

    A BaseException, so no ``except Exception`` on the way (plugin loading) swallows it.
    """

    def __init__(self, signum: int, *, ending: bool = False) -> None:
        super().__init__(signum)
        self.signum = signum
        # after the runtime's own handlers had done their work and given the CLI's back:
        # the program was on its way out, not starting
        self.ending = ending


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"; did you mean 'x'?"`` for the closest of ``choices``, or ``""``."""
    close = difflib.get_close_matches(word, list(choices), n=1)
    return f"; did you mean '{close[0]}'?" if close else ""


def install_hint(extra: str) -> str:
    """How to add an optional extra: from the package index, or in a clone of the source."""
    return f"pip install 'abh3-supervisor[{extra}]' (in a clone: pip install -e '.[{extra}]')"
