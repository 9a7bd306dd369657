"""A CPU cgroup holding a process to a share of one core, as a small computer would.

cgroup v1 (a ``cpu`` hierarchy: ``cpu.cfs_quota_us`` over ``cpu.cfs_period_us``) or v2
(a hierarchy whose ``cgroup.controllers`` has ``cpu``: ``cpu.max``), whichever this
machine mounts; the child is made next to this process's own cgroup (v1) or under the
v2 root, and removed afterwards. Needs the right to write there (root, as a benchmark on
a board runs); :func:`unavailable` says why not where it cannot be made.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from types import TracebackType

from abh3_supervisor.runtime import cgroups

PERIOD_US = 100_000  # the CFS period: a quota of 10 % is 10 ms of every 100 ms


def parent() -> tuple[Path, int] | None:
    """Where a child cgroup is made, and the cgroup version; None if no cpu controller:
    in v1 this process's own cpu cgroup (in a container the mount may be its own cgroup,
    not the hierarchy's root), in v2 the root, if it offers the cpu controller."""
    found = cgroups.cpu_hierarchy()
    if found is None:
        return None
    mount, version = found
    if version == 1:
        return cgroups.cpu_dir() or mount, 1
    controllers = mount / "cgroup.controllers"
    if controllers.exists() and "cpu" in controllers.read_text().split():
        return mount, 2
    return None


def unavailable() -> str | None:
    """Why no CPU-limited cgroup can be made here, or None."""
    found = parent()
    if found is None:
        return "no cgroup hierarchy with the cpu controller is mounted"
    where, _ = found
    if not os.access(where, os.W_OK):
        return f"{where} is not writable (run as root to limit the supervisor's CPU)"
    return None


class CpuLimit:
    """``with CpuLimit(10) as cg:`` — a cgroup limited to 10 % of one core;
    ``cg.enter`` (as a ``preexec_fn``) puts the calling process in it, or
    ``cg.add(pid)`` another; :meth:`throttled` is how often the limit held it back."""

    def __init__(self, percent: float, name: str | None = None) -> None:
        if not 0 < percent <= 100:
            raise ValueError(f"a share of one core in (0, 100] %, not {percent}")
        self.percent = percent
        self.name = name or f"abh3-small-{os.getpid()}"
        self.path: Path | None = None
        self.version = 0

    def __enter__(self) -> CpuLimit:
        if (why := unavailable()) is not None:
            raise RuntimeError(f"no CPU cgroup: {why}")
        found = parent()
        assert found is not None
        where, self.version = found
        quota = round(PERIOD_US * self.percent / 100)
        path = where / self.name
        path.mkdir(exist_ok=True)
        self.path = path
        try:
            if self.version == 1:
                (path / "cpu.cfs_period_us").write_text(str(PERIOD_US))
                (path / "cpu.cfs_quota_us").write_text(str(quota))
            else:
                # a v2 child gets the cpu controller only if its parent hands it down
                (where / "cgroup.subtree_control").write_text("+cpu")
                (path / "cpu.max").write_text(f"{quota} {PERIOD_US}")
        except OSError:
            self._remove()
            raise
        return self

    def enter(self) -> None:
        """Put the calling process in the cgroup: a ``preexec_fn``, so everything the
        command does from its first instruction counts."""
        self.add(os.getpid())

    def add(self, pid: int) -> None:
        assert self.path is not None, "only inside `with CpuLimit(…)`"
        (self.path / "cgroup.procs").write_text(str(pid))

    def throttled(self) -> dict[str, float]:
        """The cgroup's ``cpu.stat``: periods, throttled periods, throttled seconds."""
        assert self.path is not None
        stat = cgroups.cpu_stat(self.path)
        seconds = (
            stat.get("throttled_time", 0) / 1e9
            if self.version == 1
            else stat.get("throttled_usec", 0) / 1e6
        )
        return {
            "periods": stat.get("nr_periods", 0),
            "throttled": stat.get("nr_throttled", 0),
            "throttled_s": seconds,
        }

    def _remove(self) -> None:
        if self.path is None:
            return
        # a cgroup is removed only when empty: whatever is left goes back to the parent
        with contextlib.suppress(OSError):
            procs = (self.path / "cgroup.procs").read_text().split()
            for pid in procs:
                with contextlib.suppress(OSError):
                    (self.path.parent / "cgroup.procs").write_text(pid)
        with contextlib.suppress(OSError):
            self.path.rmdir()
        self.path = None

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._remove()
