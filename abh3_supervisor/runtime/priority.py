"""The bus loop's CPU priority: real-time where the system allows it.

Measured on a 2-core machine (docs/performance.md, "What keeps the bus on time"): with two
TUIs attached, the DP0 period jitter p99 was 3–5 ms whether the TUIs ran at nice 5, nice
19 or SCHED_IDLE, and whether the supervisor ran at nice 0 or nice -10 — the kernel's fair
scheduler lets a waking task wait behind a running one whatever their weights. Under
``SCHED_FIFO`` the same run kept 0.5–0.7 ms: a real-time task preempts every normal one
the moment its timer fires. So the supervisor's loop asks for ``SCHED_FIFO`` (priority
``FIFO_PRIORITY``: above every normal task, below the kernel's interrupt threads at 50).

Threads started afterwards inherit it, which the bus's own need (python-can's reader of a
bus without a file descriptor: at a lower priority, holding the GIL, it held the loop up
by 5 ms). Plugins' threads call :func:`plugin_thread` first (``PluginHost.thread_setup``):
normal priority by default, so DDS and rclpy run there (at the loop's, rclpy delivered
``cmd_vel`` late); ``BELOW_LOOP_PRIORITY`` for a plugin that asks (``abh3_threads``) —
the same lock held by a normal thread that a busy machine preempts held the loop up by
3–5 ms under an MQTT flood (docs/performance.md, "DP0 timing against the broker").
Linux throttles real-time tasks to 95 % of a CPU by default, so even a loop gone wrong
leaves the machine usable.
"""

from __future__ import annotations

import contextlib
import enum
import os
import resource
import sys
from collections.abc import Iterator

from abh3_supervisor.errors import Abh3Error
from abh3_supervisor.runtime import cgroups

FIFO_PRIORITY = 20
BELOW_LOOP_PRIORITY = FIFO_PRIORITY - 10  # plugin threads that asked (plugin_thread)
GIL_SWITCH_S = 0.0005  # the interpreter lock's switch interval while the loop is real-time
# what _may_realtime accepts, and how to give it (the shipped systemd unit does the first)
HOW_TO_ALLOW = (
    f"it needs root or an RLIMIT_RTPRIO of at least {FIFO_PRIORITY}: LimitRTPRIO={FIFO_PRIORITY} "
    f"in a systemd unit (docs/service.md), or `@group - rtprio {FIFO_PRIORITY}` in "
    "/etc/security/limits.conf"
)


def _cgroup_budget() -> str | None:
    """Why the kernel refuses real-time scheduling to a user who may ask for it, where
    it is this process's CPU cgroup (cgroup v1 with real-time group scheduling: a
    container, a CPU limit): one that gives real-time tasks no time, or None."""
    where = cgroups.cpu_dir()
    if where is None:
        return None
    runtime = where / "cpu.rt_runtime_us"
    try:
        if int(runtime.read_text()) != 0:
            return None
    except (OSError, ValueError):  # no real-time group scheduling: not the cgroup
        return None
    return (
        f"this process's CPU cgroup gives real-time tasks no time ({runtime} is 0: a "
        "container or a CPU limit): give it some, or use --priority normal"
    )


class Priority(enum.StrEnum):
    AUTO = "auto"  # real-time if this user may; normal otherwise, and say so
    REALTIME = "realtime"  # real-time, or the run does not start
    NORMAL = "normal"  # leave the scheduling as the process was started


class PriorityError(Abh3Error):
    """``--priority realtime`` where the system does not allow it (exit 2)."""


def normal() -> None:
    """The calling thread (and what it starts) at normal priority: for a program started
    from the supervisor (``preexec_fn=normal``) and for clients, which never run real-time."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def plugin_thread(below_loop: bool) -> None:
    """The calling thread (a plugin's, started by the loop's) at normal priority, or, for
    a plugin that asked and while it runs real-time, at ``BELOW_LOOP_PRIORITY``: it
    preempts the machine's other programs but never the bus loop."""
    if not below_loop:
        normal()
        return
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) == os.SCHED_FIFO:  # inherited from the real-time loop
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(BELOW_LOOP_PRIORITY))


def demote(native_id: int) -> None:
    """Thread ``native_id`` of this process to normal priority (a plugin's stuck hook)."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(native_id, os.SCHED_OTHER, os.sched_param(0))


def _may_realtime() -> bool:
    """Root, or an RLIMIT_RTPRIO that covers FIFO_PRIORITY: checked before asking, so
    CAP_SYS_NICE without the limit is not enough, and a policy systemd set beforehand
    (``CPUSchedulingPolicy=``) is not looked at."""
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return os.geteuid() == 0 or soft == resource.RLIM_INFINITY or soft >= FIFO_PRIORITY


@contextlib.contextmanager
def bus_priority(mode: Priority) -> Iterator[str]:
    """The calling thread (the bus loop's) at ``mode``'s priority, for the block; yields
    a line for the log that says what it got. Restored on the way out."""
    if mode is Priority.NORMAL or not hasattr(os, "SCHED_FIFO"):
        yield "bus loop at normal priority" + (
            "" if mode is Priority.NORMAL else " (no SCHED_FIFO here)"
        )
        return
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        if not _may_realtime():
            raise PermissionError("no permission")  # the kernel would say EPERM too
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
    except OSError as exc:
        why = f"real-time scheduling refused ({exc.strerror or exc})"
        # a user who may ask, refused all the same: the cgroup, where that is why
        how = (_may_realtime() and _cgroup_budget()) or HOW_TO_ALLOW
        if mode is Priority.REALTIME:
            raise PriorityError(f"--priority realtime: {why}; {how}") from exc
        yield f"bus loop at normal priority: {why}; {how}"
        return
    # the loop woken while another thread of ours runs Python waits for the interpreter
    # lock up to the switch interval: 5 ms by default, the whole jitter budget
    switch = sys.getswitchinterval()
    sys.setswitchinterval(GIL_SWITCH_S)
    try:
        yield f"bus loop at real-time priority (SCHED_FIFO {FIFO_PRIORITY})"
    finally:
        sys.setswitchinterval(switch)
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, before[0], before[1])
