"""This process's CPU cgroup: where its limits are read (a container, a CPU quota).

Linux offers the ``cpu`` controller either in a cgroup v1 hierarchy of its own or in the
unified v2 one; a hybrid system mounts both and puts ``cpu`` in v1. Reading only: the
supervisor never changes its cgroup.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

MOUNTS = Path("/proc/self/mounts")  # where the hierarchies are mounted …
OWN = Path("/proc/self/cgroup")  # … and where in them this process is


def cpu_dir() -> Path | None:
    """The directory of this process's cgroup that holds its ``cpu.*`` files, or None."""
    with contextlib.suppress(OSError, ValueError):
        mounts = [line.split() for line in MOUNTS.read_text().splitlines()]
        v1 = next((f[1] for f in mounts if f[2] == "cgroup" and "cpu" in f[3].split(",")), None)
        v2 = next((f[1] for f in mounts if f[2] == "cgroup2"), None)
        for entry in OWN.read_text().splitlines():
            hierarchy, controllers, path = entry.split(":", 2)
            if v1 is not None and "cpu" in controllers.split(","):
                where = Path(v1) / path.lstrip("/")
            elif v1 is None and v2 is not None and hierarchy == "0":
                where = Path(v2) / path.lstrip("/")
            else:
                continue
            return where if where.is_dir() else None
    return None


class Throttling:
    """``held()``: whether the cgroup's CPU quota held this process back since the last
    call (its ``cpu.stat``'s ``nr_throttled`` grew); never, where there is no quota."""

    def __init__(self, directory: Path | None) -> None:
        self.stat = None if directory is None else directory / "cpu.stat"
        self._seen = self._count()

    def _count(self) -> int:
        if self.stat is None:
            return 0
        try:
            for line in self.stat.read_text().splitlines():
                key, _, value = line.partition(" ")
                if key == "nr_throttled":
                    return int(value)
        except (OSError, ValueError):
            self.stat = None  # gone or unreadable: not asked again
        return 0

    def held(self) -> bool:
        count = self._count()
        grew, self._seen = count > self._seen, count
        return grew
