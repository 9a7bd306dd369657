"""Every signal whose default action ends the process, and what abh3 does with it.

The one place the signal handling of every command is decided (docs/signals.md is the
same table in words). Catchable signals that would end the process go through the normal
way out: the drives get the safe word, their stops are confirmed, the recordings closed.
SIGPIPE and SIGXFSZ are ignored: the write that raised them fails instead (EPIPE, EFBIG),
which the code writing already handles. Synchronous faults and SIGKILL/SIGSTOP cannot be
handled by the process: the drive's own command-zero timeout (``drive_timeout_ms``,
parameter 0x4117) stops it. Job control's stops (SIGTSTP, SIGTTIN, SIGTTOU) are ignored
while a bus is held: a suspended supervisor commands its drives no more than a dead one.

Only the standard library is imported: the CLI catches these before anything else loads.
"""

from __future__ import annotations

import contextlib
import enum
import faulthandler
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import asyncio
    from types import FrameType


class Action(enum.Enum):
    STOP = "the normal way out"
    IGNORE = "ignored: the write that raised it fails instead"
    FAULT = "cannot be handled: the drive's command-zero timeout stops it"
    UNCATCHABLE = "cannot be caught: the drive's command-zero timeout stops it"
    JOB_CONTROL = "ignored while a bus is held: the drives stay supervised"


@dataclass(frozen=True)
class Entry:
    name: str
    default: str  # signal(7): "terminate" or "core dump"
    action: Action
    why: str


_T, _C = "terminate", "core dump"
_S, _I, _F, _U = Action.STOP, Action.IGNORE, Action.FAULT, Action.UNCATCHABLE
_J = Action.JOB_CONTROL
_JOB_WHY = (
    "job control (Ctrl-Z, a background job at its terminal) would suspend the process "
    "and leave the drives commanded by nobody until their own timeout"
)
_FAULT_WHY = (
    "raised by the faulting instruction itself: a handler that returns re-runs it, and "
    "the interpreter's state cannot be trusted; faulthandler prints every thread's "
    "Python traceback on stderr, then the process ends"
)
_KILL_WHY = "the kernel does not let a process catch it"
# signal(7)'s terminating signals on Linux (the real-time ones are added below)
TABLE: tuple[Entry, ...] = (
    Entry("SIGHUP", _T, _S, "the terminal or the session went away"),
    Entry("SIGINT", _T, _S, "Ctrl-C"),
    Entry("SIGTERM", _T, _S, "kill, systemd's stop, the TUI quitting its child"),
    Entry("SIGQUIT", _C, _S, "Ctrl-\\ on a terminal: a stop asked for, not a fault"),
    Entry("SIGUSR1", _T, _S, "sent by hand or a script; abh3 gives it no other meaning"),
    Entry("SIGUSR2", _T, _S, "sent by hand or a script; abh3 gives it no other meaning"),
    Entry("SIGALRM", _T, _S, "abh3 sets no alarm: one comes from outside"),
    Entry("SIGVTALRM", _T, _S, "abh3 sets no virtual timer: one comes from outside"),
    Entry("SIGPROF", _T, _S, "abh3 sets no profiling timer: one comes from outside"),
    Entry(
        "SIGXCPU",
        _C,
        _S,
        "the soft CPU-time limit (RLIMIT_CPU, systemd's LimitCPU=soft:hard): the stop "
        "must be over before the hard limit's SIGKILL",
    ),
    Entry("SIGIO", _T, _S, "abh3 asks for no signal-driven I/O: one comes from outside"),
    Entry("SIGPWR", _T, _S, "a power failure announced (a UPS daemon, init)"),
    Entry("SIGSTKFLT", _T, _S, "unused by the kernel: one comes from outside"),
    Entry("SIGTRAP", _C, _S, "a debugger's; without one, sent from outside"),
    Entry("SIGSYS", _C, _S, "a system call refused by a seccomp filter that traps"),
    Entry(
        "SIGABRT",
        _C,
        _S,
        "sent from outside it is a stop asked for; abort() inside the process (a C "
        "library's failed assertion) ends it whatever the handler: the drive's timeout",
    ),
    Entry(
        "SIGPIPE",
        _T,
        _I,
        "a reader gone (`abh3 decode … | head`, a closed log pipe): the write fails with "
        "EPIPE and the code writing says so; the drives go on as they were",
    ),
    Entry(
        "SIGXFSZ",
        _C,
        _I,
        "a file over RLIMIT_FSIZE: the write fails with EFBIG, which ends that recording "
        "with one line as a full disk does (exit 5), and the drives go on",
    ),
    Entry("SIGSEGV", _C, _F, _FAULT_WHY),
    Entry("SIGBUS", _C, _F, _FAULT_WHY),
    Entry("SIGFPE", _C, _F, _FAULT_WHY),
    Entry("SIGILL", _C, _F, _FAULT_WHY),
    Entry("SIGKILL", _T, _U, _KILL_WHY),
    Entry("SIGSTOP", "stop", _U, _KILL_WHY + " (the process stops, not ends)"),
    # not terminating, but suspending a process that holds a bus is as bad
    Entry("SIGTSTP", "stop", _J, _JOB_WHY),
    Entry("SIGTTIN", "stop", _J, _JOB_WHY),
    Entry("SIGTTOU", "stop", _J, _JOB_WHY),
)


def _number(name: str) -> int | None:
    sig = getattr(signal, name, None)
    return None if sig is None else int(sig)


def _of(action: Action) -> tuple[int, ...]:
    found = (_number(e.name) for e in TABLE if e.action is action)
    return tuple(n for n in found if n is not None)


# every signal whose default action ends the process and that we can catch: the normal
# way out. The real-time signals' default action is to terminate too.
STOP_SIGNALS: tuple[int, ...] = _of(Action.STOP) + tuple(
    range(signal.SIGRTMIN, signal.SIGRTMAX + 1) if hasattr(signal, "SIGRTMIN") else ()
)
IGNORED: tuple[int, ...] = _of(Action.IGNORE)
FAULTS: tuple[int, ...] = _of(Action.FAULT)
JOB_CONTROL: tuple[int, ...] = _of(Action.JOB_CONTROL)


def name(signum: int) -> str:
    """``SIGUSR1``; a real-time signal as ``SIGRTMIN+3`` (``signal.Signals`` names none)."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        if hasattr(signal, "SIGRTMIN") and signal.SIGRTMIN < signum <= signal.SIGRTMAX:
            return f"SIGRTMIN+{signum - signal.SIGRTMIN}"
        return f"signal {signum}"


def ignore_harmless() -> None:
    """SIGPIPE and SIGXFSZ ignored (Python does so at start-up; an embedding may not)."""
    for sig in IGNORED:
        signal.signal(sig, signal.SIG_IGN)


def report_faults() -> None:
    """A fault prints every thread's Python traceback on stderr before the process ends."""
    if faulthandler.is_enabled():
        return
    with contextlib.suppress(AttributeError, ValueError, OSError):  # stderr without a file
        faulthandler.enable(sys.stderr, all_threads=True)


def ignore_stops() -> None:
    """The way out is over and the process ends: a stop signal that comes now, while the
    interpreter winds down, changes neither the exit code nor prints a traceback (the
    defaults would end the process by that signal instead)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


_Handler = Callable[[int, "FrameType | None"], object]


def catch(handler: _Handler) -> dict[int, object]:
    """Python-level ``handler`` for every stop signal; the handlers it replaced, for
    :func:`restore` (for code that must run while the loop is blocked, or before one)."""
    return {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}


def restore(saved: Mapping[int, object]) -> None:
    """The handlers :func:`catch` replaced. One installed from C (faulthandler's, under
    ``PYTHONFAULTHANDLER``) reads as None and cannot be put back: the default then."""
    for sig, handler in saved.items():
        if callable(handler) or isinstance(handler, int):
            signal.signal(sig, handler)
        else:
            signal.signal(sig, signal.SIG_DFL)


_took_over = 0  # on_loop blocks begun on the main thread in this process


def took_over() -> int:
    """How many times a loop's handlers (:func:`on_loop`) took over the stop signals in
    this process: a handler installed before can tell whether the way out is the loop's."""
    return _took_over


@contextlib.contextmanager
def on_loop(
    loop: asyncio.AbstractEventLoop, caught: Callable[[int], None]
) -> Iterator[tuple[int, ...]]:
    """``caught(signum)`` on ``loop`` for every stop signal while the block runs (every
    time one comes: a second one must change nothing), and job control ignored; the
    handlers before it come back after — unless a stop signal came: the way out it began
    is then over, and the stop signals stay ignored (a second Ctrl-C a few milliseconds
    after a quick way out met Python's KeyboardInterrupt, or the CLI's "stopped while
    starting"). Yields the signals handled (none off the main thread: signals reach only
    it)."""
    global _took_over
    if threading.current_thread() is not threading.main_thread():
        yield ()
        return
    _took_over += 1
    ignore_harmless()
    report_faults()
    saved = {sig: signal.getsignal(sig) for sig in (*STOP_SIGNALS, *JOB_CONTROL)}
    stopped: list[int] = []

    def on_signal(signum: int) -> None:
        stopped.append(signum)
        caught(signum)

    for sig in JOB_CONTROL:
        signal.signal(sig, signal.SIG_IGN)
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, on_signal, sig)
    try:
        yield STOP_SIGNALS
    finally:
        # held back while the handlers change: asyncio puts the defaults back as it
        # removes its own, and one coming then would meet them
        signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
        try:
            for sig in STOP_SIGNALS:
                loop.remove_signal_handler(sig)
            restore(saved)
            if stopped:
                ignore_stops()  # what was held back is dropped with it
        finally:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
