"""A network namespace with nothing but ``lo``, for a shared bus that must not leave the
machine.

A multicast group's datagrams go out on the machine's network even with a hop limit of
1. Inside a namespace of its own, whose only interface is the loopback, a
``udp_multicast`` bus reaches every process started in it and nothing else. Tests and
benchmarks start ``abh3 simulate``, supervisors and listeners in one (docs/simulator.md
shows the same by hand). Linux only; needs ``unshare``, ``nsenter`` and ``ip``, and the
right to make a namespace (root, or user namespaces).
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Sequence
from types import TracebackType
from typing import Any

# the loopback, up, with multicast on and the groups routed to it: python-can's
# udp_multicast joins its group on "any" interface, which needs a route; its source
# address gives our frames one the kernel can keep our own copies from us by
# (simulator/multicast.py)
SETUP = (
    "ip link set lo up && ip link set lo multicast on"
    " && ip route add 239.0.0.0/8 dev lo src 127.0.0.1"
)


def unavailable() -> str | None:
    """Why no namespace can be made here, or None."""
    missing = [t for t in ("unshare", "nsenter", "ip") if shutil.which(t) is None]
    if missing:
        return f"not installed: {', '.join(missing)}"
    probe = subprocess.run(
        ["unshare", "-n", "sh", "-c", SETUP], capture_output=True, text=True, check=False
    )
    if probe.returncode != 0:
        return f"no network namespace with a multicast loopback: {probe.stderr.strip()}"
    return None


class Namespace:
    """``with Namespace() as ns:`` — a namespace held open by a sleeping process;
    :meth:`popen` starts a command inside it (its pid is the command's own: nsenter
    execs it, so a signal to it reaches the command)."""

    def __init__(self) -> None:
        self._holder: subprocess.Popen[str] | None = None

    def __enter__(self) -> Namespace:
        self._holder = subprocess.Popen(
            ["unshare", "-n", "sh", "-c", f"{SETUP} && echo ready && exec sleep infinity"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self._holder.stdout is not None
        if self._holder.stdout.readline().strip() != "ready":
            err = self._holder.communicate(timeout=10)[1]
            raise RuntimeError(f"no network namespace: {err.strip()}")
        return self

    @property
    def pid(self) -> int:
        assert self._holder is not None, "only inside `with Namespace()`"
        return self._holder.pid

    def command(self, argv: Sequence[str]) -> list[str]:
        """``argv`` as run inside the namespace."""
        return ["nsenter", "-t", str(self.pid), "-n", "--", *argv]

    def popen(self, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen[str]:
        return subprocess.Popen(self.command(argv), text=True, **kwargs)

    def run(self, argv: Sequence[str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
        return subprocess.run(self.command(argv), text=True, check=False, **kwargs)

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._holder is not None:
            self._holder.kill()
            self._holder.communicate()
            self._holder = None
