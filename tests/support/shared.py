"""Processes on one shared bus, inside a network namespace with only ``lo``.

``abh3 simulate`` (the drives, answering on stdin, tracing what they do), supervisors
(``abh3 run --headless``), and an independent listener (python-can's own ``can.logger``:
none of our code) — all on ``udp_multicast`` in a :class:`Namespace`, so nothing leaves
the machine. Waits are for conditions (a line, an event), never fixed sleeps; the one
timed thing is a window in which something must *not* happen.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import can
import pytest

from abh3_supervisor.protocol import ids
from abh3_supervisor.runtime.netns import Namespace, unavailable

GROUP = "239.74.163.2"
# two drives turning at 300 min⁻¹ from the start, 50 Hz commands, 0x4117 = 300 ms
MOVING_PAIR = f"""
buses:
  main:
    interface: udp_multicast
    channel: {GROUP}
    simulate:
      startup:
        left: ["SERVO ON ON", "START ON ON", "VEL 300 0"]
        right: ["SERVO ON ON", "START ON ON", "VEL 300 0"]
units:
  - {{name: left, bus: main, abh3_id: 1, command_rate_hz: 50, drive_timeout_ms: 300}}
  - {{name: right, bus: main, abh3_id: 3, command_rate_hz: 50, drive_timeout_ms: 300}}
"""
ABH3 = [sys.executable, "-m", "abh3_supervisor"]


def namespace_or_skip() -> Namespace:
    why = unavailable()
    if why is not None:
        pytest.skip(f"no shared bus here: {why}")
    return Namespace()


def wait_for(what: str, predicate: Callable[[], Any], timeout: float = 10.0) -> Any:
    """``predicate()``'s first true value, polled, or a failure saying what never came."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"within {timeout} s: {what}")
        time.sleep(0.01)


def window(seconds: float) -> None:
    """Let ``seconds`` pass: a window in which something must NOT happen (a motor that
    must stay still), not a wait for something to happen (that is :func:`wait_for`)."""
    time.sleep(seconds)


class Lines:
    """A process's output lines, read by a thread as they come."""

    def __init__(self, stream: IO[str]) -> None:
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.put(line.rstrip("\n"))

    def next(self, timeout: float = 10.0) -> str:
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            pytest.fail(f"no line within {timeout} s (so far: {self.seen[-5:]})")
        self.seen.append(line)
        return line


@dataclass
class Simulator:
    proc: subprocess.Popen[str]
    out: Lines
    trace_path: Path

    def tell(self, line: str) -> str:
        """One command on its stdin; its answer (the first line)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return self.out.next()

    def events(self, unit: str | None = None, kind: str | None = None) -> list[dict[str, Any]]:
        out = []
        for line in self.trace_path.read_text().splitlines():
            try:
                event = json.loads(line)
            except ValueError:  # a line being written
                continue
            if (unit is None or event["unit"] == unit) and (kind is None or event["event"] == kind):
                out.append(event)
        return out

    def wait_event(self, unit: str, kind: str, after: float = 0.0, timeout: float = 10.0) -> Any:
        return wait_for(
            f"{unit}: {kind} after {after}",
            lambda: next((e for e in self.events(unit, kind) if e["t"] >= after), None),
            timeout,
        )


@dataclass
class Supervisor:
    proc: subprocess.Popen[str]
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_log(self, text: str, timeout: float = 10.0) -> None:
        wait_for(f"the supervisor logs {text!r}", lambda: text in self.log(), timeout)


@dataclass
class SharedBus:
    ns: Namespace
    tmp: Path
    config: Path
    procs: list[subprocess.Popen[str]] = field(default_factory=list)

    def simulator(self, config: Path | None = None, extra: tuple[str, ...] = ()) -> Simulator:
        trace = self.tmp / "trace.jsonl"
        proc = self.ns.popen(
            [*ABH3, "simulate", str(config or self.config), "--trace", str(trace), *extra],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=(self.tmp / "simulate.err").open("w"),
        )
        self.procs.append(proc)
        assert proc.stdout is not None
        sim = Simulator(proc, Lines(proc.stdout), trace)
        assert sim.out.next(30).startswith("ready: bus "), (self.tmp / "simulate.err").read_text()
        return sim

    def supervisor(self, name: str, *args: str, config: Path | None = None) -> Supervisor:
        log_path = self.tmp / f"{name}.err"
        proc = self.ns.popen(
            [*ABH3, "run", str(config or self.config), "--headless", *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=log_path.open("w"),
        )
        self.procs.append(proc)
        return Supervisor(proc, log_path)

    def running(self, name: str = "sup") -> tuple[Simulator, Listener, Supervisor]:
        """The drives, a listener, and a supervisor driving them (``--no-socket``)."""
        sim = self.simulator()
        listener = self.listener()
        listener.wait_started()
        return sim, listener, self.supervisor(name, "--no-socket")

    def listener(self) -> Listener:
        path = self.tmp / "listener.log"
        proc = self.ns.popen(
            [
                sys.executable,
                "-m",
                "can.logger",
                "-i",
                "udp_multicast",
                "-c",
                GROUP,
                "-f",
                str(path),
            ],
            stdout=subprocess.DEVNULL,
            stderr=(self.tmp / "listener.err").open("w"),
        )
        self.procs.append(proc)
        return Listener(proc, path)

    def abh3(self, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        return self.ns.run([*ABH3, *args], capture_output=True, timeout=timeout)

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@dataclass
class Listener:
    proc: subprocess.Popen[str]
    path: Path

    def frames(self) -> list[can.Message]:
        """Every frame it heard, once stopped (python-can's logger flushes on SIGINT)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            self.proc.wait(timeout=15)
        return list(can.LogReader(str(self.path)))

    def wait_started(self) -> None:
        wait_for("the listener opens its file", self.path.exists)


def commands_to(frames: list[can.Message], drive: int) -> list[can.Message]:
    """The DP0 commands (host → ``drive``) among ``frames``."""
    out = []
    for msg in frames:
        cid = ids.CanId.from_int(msg.arbitration_id)
        if cid.pf == ids.PF_SINGLE and cid.ps == drive and len(msg.data) == 8:
            out.append(msg)
    return out


@contextlib.contextmanager
def shared_bus(tmp: Path, config_text: str) -> Iterator[SharedBus]:
    config = tmp / "robot.yaml"
    config.write_text(config_text)
    with namespace_or_skip() as ns:
        bus = SharedBus(ns, tmp, config)
        try:
            yield bus
        finally:
            bus.close()
