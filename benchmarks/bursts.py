"""Bursts of clients against a recorded headless run: the DP0 gaps they cause.

``abh3 run configs/demo.yaml --headless --record run.log`` (two units at 50 Hz) serves its
control socket; while it runs, this process opens ``flood`` connections at once (each asks
``hello`` and reads its answer, a result or the refusal past 32 clients) and then makes
``cycles`` connect/``hello``/close cycles one after another, as a misbehaving script or an
attacker would. The figure is the longest gap between two DP0 commands to the same drive,
in command periods, read from the CAN recording over the burst (the stop path's own
50 ms cadence at the end is outside that window). Run alone:
``python -m benchmarks.bursts [--flood N] [--cycles N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import selectors
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can

from abh3_supervisor.protocol import ids

ROOT = Path(__file__).resolve().parent.parent
CONFIG = "configs/demo.yaml"
DRIVES = (1, 3)  # configs/demo.yaml's abh3_id of left and right, host 2, 50 Hz
PERIOD_S = 1 / 50
HELLO = b'{"jsonrpc":"2.0","id":1,"method":"hello"}\n'


@dataclass
class Burst:
    """What the clients saw and what the bus did meanwhile."""

    accepted: int = 0  # answered with a result
    refused: int = 0  # answered with an error (too many clients)
    failed: int = 0  # no answer: reset, closed, or not readable in time
    cycles: int = 0
    worst_gap_periods: float = 0.0


def flood(path: Path, count: int, hold: float = 1.0, timeout: float = 20.0) -> Burst:
    """``count`` connections opened together, each asking ``hello``; all answers read,
    the connections are held ``hold`` seconds longer, then closed together."""
    seen = Burst()
    socks: list[socket.socket] = []
    sel = selectors.DefaultSelector()
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            sock.connect(str(path))  # a full backlog makes this wait: the kernel absorbs it
            sock.setblocking(False)
            socks.append(sock)
        for sock in socks:
            with contextlib.suppress(OSError):  # refused and closed: read what it was told
                sock.send(HELLO)
            sel.register(sock, selectors.EVENT_READ, bytearray())
        deadline = time.monotonic() + timeout
        while sel.get_map() and time.monotonic() < deadline:
            for key, _ in sel.select(0.5):
                _read_answer(key, sel, seen)
        seen.failed += len(sel.get_map())
        time.sleep(hold)  # the load's shape: a crowd that stays a while
    finally:
        sel.close()
        for sock in socks:
            sock.close()
    return seen


def _read_answer(key: selectors.SelectorKey, sel: selectors.BaseSelector, seen: Burst) -> None:
    sock, buf = key.fileobj, key.data
    assert isinstance(sock, socket.socket) and isinstance(buf, bytearray)
    try:
        data = sock.recv(65536)
    except BlockingIOError:
        return
    except OSError:
        data = b""
    buf += data
    if b"\n" in buf:
        reply = json.loads(buf.split(b"\n", 1)[0])
        if "result" in reply:
            seen.accepted += 1
        else:
            seen.refused += 1
    elif data:
        return
    else:
        seen.failed += 1
    sel.unregister(sock)


def churn(path: Path, cycles: int) -> int:
    """Connect, ask ``hello``, close — ``cycles`` times, as fast as the socket allows."""
    for _ in range(cycles):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.connect(str(path))
            with contextlib.suppress(OSError):
                sock.sendall(HELLO)
    return cycles


def settled(path: Path) -> None:
    """One more ``hello`` answered: the service has handled what came before it."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.connect(str(path))  # blocking: waits its place in a full backlog
        sock.settimeout(20)
        sock.sendall(HELLO)
        with sock.makefile("rb") as reader:
            reader.readline()


def dp0_gaps(record: Path, start: float, end: float) -> float:
    """The longest gap between DP0 commands to one drive in [start, end], in periods."""
    wanted = {ids.dp0_command_id(abh3, 2): abh3 for abh3 in DRIVES}
    times: dict[int, list[float]] = {abh3: [] for abh3 in DRIVES}
    for msg in can.LogReader(str(record)):
        abh3 = wanted.get(msg.arbitration_id)
        if abh3 is not None and start <= msg.timestamp <= end:
            times[abh3].append(msg.timestamp)
    gaps = [b - a for t in times.values() for a, b in itertools.pairwise(t)]
    if not gaps:
        raise RuntimeError(f"{record}: no DP0 commands between {start} and {end}")
    return max(gaps) / PERIOD_S


@contextlib.contextmanager
def recorded_run(tmp: Path) -> Iterator[tuple[Path, Path]]:
    """The demo headless, recording, serving a socket; yields (socket, recording) once
    both units are online, and leaves once it has stopped (exit 0)."""
    sock, record = tmp / "s" / "demo.sock", tmp / "run.log"
    args = ["--headless", "--socket", str(sock), "--record", str(record), "--status-interval", "0"]
    run = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", CONFIG, *args],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert run.stderr is not None
    try:
        for line in run.stderr:
            if "unit right: online" in line:
                break
        else:
            raise RuntimeError(f"the supervisor ended before both units were online: {line}")
        yield sock, record
    finally:
        run.terminate()
        rest = run.stderr.read()
        if run.wait(30) != 0:
            raise RuntimeError(f"the supervisor ended with {run.returncode}: {rest[-2000:]}")


def measure(flood_count: int, cycles: int) -> Burst:
    with tempfile.TemporaryDirectory(dir="/tmp") as tmp:
        with recorded_run(Path(tmp)) as (sock, record):
            start = time.time()
            seen = flood(sock, flood_count) if flood_count else Burst()
            seen.cycles = churn(sock, cycles)
            settled(sock)  # answered: everything before it was handled
            end = time.time()
        seen.worst_gap_periods = dp0_gaps(record, start - 0.2, end)
    return seen


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.bursts", description=__doc__)
    p.add_argument("--flood", type=int, default=200, help="connections at once (default 200)")
    p.add_argument("--cycles", type=int, default=3000, help="connect/close cycles (default 3000)")
    a = p.parse_args(argv)
    seen = measure(a.flood, a.cycles)
    print(seen)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
