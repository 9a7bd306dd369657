"""This process's CPU cgroup: where its limits are read (a container, a CPU quota).

Linux offers the ``cpu`` controller either in a cgroup v1 hierarchy of its own or in the
unified v2 one; a hybrid system mounts both and puts ``cpu`` in v1. Reading only: the
supervisor never changes its cgroup (section 12's benchmark makes one where these
functions find the hierarchy: benchmarks/cgroup.py).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

MOUNTS = Path("/proc/self/mounts")  # where the hierarchies are mounted …
OWN = Path("/proc/self/cgroup")  # … and where in them this process is


def cpu_hierarchy() -> tuple[Path, int] | None:
    """Where the hierarchy with the ``cpu`` controller is mounted, and its version: a v1
    one of its own where there is one (a hybrid system puts ``cpu`` there), else the
    unified v2 one; None where neither is mounted (or /proc cannot be read)."""
    with contextlib.suppress(OSError, ValueError):
        mounts = [line.split() for line in MOUNTS.read_text().splitlines()]
        v1 = next((f[1] for f in mounts if f[2] == "cgroup" and "cpu" in f[3].split(",")), None)
        if v1 is not None:
            return Path(v1), 1
        v2 = next((f[1] for f in mounts if f[2] == "cgroup2"), None)
        if v2 is not None:
            return Path(v2), 2
    return None


def cpu_dir() -> Path | None:
    """The directory of this process's cgroup that holds its ``cpu.*`` files, or None."""
    found = cpu_hierarchy()
    if found is None:
        return None
    mount, version = found
    with contextlib.suppress(OSError, ValueError):
        for entry in OWN.read_text().splitlines():
            hierarchy, controllers, path = entry.split(":", 2)
            # v1: the line of the hierarchy with the cpu controller; v2: hierarchy 0's
            ours = "cpu" in controllers.split(",") if version == 1 else hierarchy == "0"
            if ours:
                where = mount / path.lstrip("/")
                return where if where.is_dir() else None
    return None


def cpu_stat(directory: Path) -> dict[str, int]:
    """A cgroup's ``cpu.stat``: its counters by name (v1 and v2 name them differently)."""
    pairs = (line.split() for line in (directory / "cpu.stat").read_text().splitlines())
    return {key: int(value) for key, value in pairs}


class Throttling:
    """``held()``: whether the cgroup's CPU quota held this process back since the last
    call (its ``cpu.stat``'s ``nr_throttled`` grew); never, where there is no quota."""

    def __init__(self, directory: Path | None) -> None:
        self.directory = directory
        self._seen = self._count()

    def _count(self) -> int:
        if self.directory is None:
            return 0
        try:
            return cpu_stat(self.directory).get("nr_throttled", 0)
        except (OSError, ValueError):
            self.directory = None  # gone or unreadable: not asked again
        return 0

    def held(self) -> bool:
        count = self._count()
        grew, self._seen = count > self._seen, count
        return grew
