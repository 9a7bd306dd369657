"""10. The supervisor alone: its drives in an ``abh3 simulate`` process of their own.

Every other section runs the simulated drives in the process it measures, so their CPU
is in the figures. Here the drives run in ``abh3 simulate`` on python-can's
``udp_multicast`` bus, inside a network namespace whose only interface is ``lo`` (the
bus never leaves the machine: runtime/netns.py), and each process is timed on its own:

* **the supervisor** — ``abh3 run --headless --no-socket`` (no recording), N units;
* **a bare python-can host** — this module's ``bare`` role: every period, for each drive,
  build a DP0 message, send it, ``recv`` until its reply — the least a Python host does.
  Its own frames are dropped in the kernel as the supervisor's are (the same
  ``own_sender`` of simulator/multicast.py: the frames go out on a socket of their own
  whose copies a socket filter on the bus keeps away), so that neither host pays for
  reading its own echo and the two figures compare like with like; python-can packs
  each frame and reads the replies (``recv``) as for any python-can program;
* **the simulator process**, during the supervisor's window (no target: its share is what
  the in-process figures used to include);
* with ``sizing`` (not ``--quick``), the supervisor's CPU for 16 units — section 4's
  sizing row, the one a small computer is chosen by — without the simulator's.

The ``--runs`` windows of the supervisor and of the bare host alternate — supervisor, bare
host, supervisor, bare host … (``--no-interleave``: every supervisor window first) — in
one namespace on one simulator, so that each run's pair shares the machine's state of the
moment; each row prints the median and the spread (min–max), and the CPU-per-exchange
target must hold in every run's pair, not only in the medians.

CPU is each process's run time (the scheduler's, per thread) over a fixed window; exchanges
(DP0 replies), rates and the command period's jitter are read off the wire by a
listener in the namespace (this module's ``listen`` role: python-can timestamps each
datagram in the kernel, SO_TIMESTAMPNS, so a timestamp is when the frame was sent, not
when the listener got to it). The baselines with the drives in-process are the same
``abh3 run`` on ``interface: virtual, simulate: true`` — timed from its own ``--record``
(the time each command frame left the pump), and, without a recording, for its CPU.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
from can.interfaces.udp_multicast.utils import pack_message

from abh3_supervisor.protocol import frames, ids
from abh3_supervisor.runtime import netns
from abh3_supervisor.scheduler.stats import percentile
from abh3_supervisor.simulator.multicast import own_sender
from benchmarks.report import Row, machine, print_rows

ROOT = Path(__file__).resolve().parent.parent  # where `benchmarks` imports
CHANNEL = "239.74.163.2"
HOST = 100
UNITS, RATE = 4, 100.0
SECTION = (
    "10. the supervisor alone (drives in `abh3 simulate`, udp_multicast in a netns with only lo)"
)
WARMUP_S = 1.0  # after the start: start-up verification done, the loop settled
START_TIMEOUT_S = 30.0


def config(units: int, rate: float, interface: str) -> str:
    listed = "".join(
        f"  - {{name: u{i}, bus: b, abh3_id: {i + 1}, host_id: {HOST}, "
        f"command_rate_hz: {rate:g}, broadcast: {{mask: 0}}}}\n"
        for i in range(units)
    )
    channel = CHANNEL if interface == "udp_multicast" else f"alone-{os.getpid()}"
    bitrate = 500_000 if units <= 8 else 1_000_000  # 16 at 100 Hz: 102 % of 500 kbit/s at worst
    bus = f"b: {{interface: {interface}, channel: {channel}, bitrate: {bitrate}, simulate: true}}"
    return f"buses:\n  {bus}\nunits:\n{listed}"


def cpu_times(pid: int) -> dict[str, int]:
    """Nanoseconds each thread of ``pid`` has run so far (/proc/PID/task/*/schedstat: the
    scheduler's own count, not sampled at clock ticks)."""
    times: dict[str, int] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that just ended
            times[task.name] = int((task / "schedstat").read_text().split()[0])
    return times


def cpu_between(before: dict[str, int], after: dict[str, int]) -> float:
    """CPU seconds between two :func:`cpu_times` (a thread that started and ended in
    between is not seen: none of the processes timed here makes such threads)."""
    return sum(ns - before.get(tid, 0) for tid, ns in after.items()) / 1e9


def _wait_for(
    what: str, ready: Callable[[], bool], proc: subprocess.Popen[str], said: Callable[[], str]
) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not ready():
        if proc.poll() is not None:
            raise RuntimeError(f"{what}: the process ended (exit {proc.returncode}){said()}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what}: not within {START_TIMEOUT_S:g} s")
        time.sleep(0.02)


def _line(proc: subprocess.Popen[str], what: str) -> str:
    """The next line the process prints: it says so when it is ready."""
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], START_TIMEOUT_S)
    if not ready:
        raise RuntimeError(f"{what}: not ready within {START_TIMEOUT_S:g} s")
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError(f"{what}: ended before it was ready (exit {proc.wait(10)})")
    return line.strip()


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@dataclass
class Window:
    start: float  # wall clock, as the kernel's timestamps
    end: float
    cpu: dict[str, float]  # CPU seconds per process in the window


def _measure(pids: dict[str, int], seconds: float) -> Window:
    """Each process's CPU over a window of ``seconds`` (wall clock) from now."""
    before = {name: cpu_times(pid) for name, pid in pids.items()}
    start = time.time()
    time.sleep(seconds)  # the measuring window itself
    end = time.time()
    cpu = {name: cpu_between(before[name], cpu_times(pid)) for name, pid in pids.items()}
    return Window(start, end, cpu)


def _supervisor_window(
    ns: netns.Namespace | None, cfg: Path, sim_pid: int | None, seconds: float, log: Path
) -> Window:
    """``abh3 run`` on ``cfg`` (in ``ns`` if given), measured for ``seconds`` after warm-up."""
    argv = [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless",
            "--no-socket", "--status-interval", "0"]  # fmt: skip
    with log.open("w") as err:
        sup = subprocess.Popen(
            ns.command(argv) if ns is not None else argv,
            text=True, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err,
        )  # fmt: skip
    try:
        _wait_for(
            "abh3 run started its units",
            lambda: "running " in log.read_text(),
            sup,
            lambda: f":\n{log.read_text()}",
        )
        time.sleep(WARMUP_S)
        pids = {"supervisor": sup.pid} | ({"simulator": sim_pid} if sim_pid else {})
        window = _measure(pids, seconds)
        if sup.poll() is not None:
            raise RuntimeError(f"abh3 run ended during the window:\n{log.read_text()}")
        return window
    finally:
        _stop(sup)


def _bare_window(ns: netns.Namespace, sim_pid: int, seconds: float) -> Window:
    bare = ns.popen(
        [sys.executable, "-m", "benchmarks.alone", "bare", "--units", str(UNITS),
         "--rate", str(RATE)],
        cwd=ROOT, stdout=subprocess.PIPE,
    )  # fmt: skip
    try:
        if (said := _line(bare, "the bare python-can host")) != "started":
            raise RuntimeError(f"the bare python-can host: {said}")
        time.sleep(WARMUP_S)
        return _measure({"bare": bare.pid, "simulator": sim_pid}, seconds)
    finally:
        _stop(bare)


@dataclass
class Wire:
    """DP0 frames the listener heard: (timestamp, id), in order."""

    frames: list[tuple[float, int]]
    units: int = UNITS

    def exchanges(self, w: Window) -> int:
        replies = {ids.dp0_reply_id(i + 1, HOST) for i in range(self.units)}
        return sum(1 for t, i in self.frames if w.start <= t <= w.end and i in replies)

    def timing(self, w: Window) -> dict[str, float]:
        by_unit: dict[int, list[float]] = defaultdict(list)
        commands = {ids.dp0_command_id(i + 1, HOST): i for i in range(self.units)}
        for t, i in self.frames:
            if w.start <= t <= w.end and i in commands:
                by_unit[commands[i]].append(t)
        return timing(by_unit, RATE, self.units)


def timing(by_unit: dict[int, list[float]], rate: float, units: int) -> dict[str, float]:
    """Worst unit's rate error and the command period's jitter, from send times."""
    period = 1.0 / rate
    jitter: list[float] = []
    rates: list[float] = []
    for times in by_unit.values():
        jitter += [abs((b - a) - period) for a, b in itertools.pairwise(times)]
        if len(times) > 1:
            rates.append((len(times) - 1) / (times[-1] - times[0]))
    if len(rates) < units:
        raise RuntimeError(f"commands to only {len(rates)} of {units} units were seen")
    return {
        "rate_error_percent": 100 * max(abs(r - rate) / rate for r in rates),
        "jitter_p99_ms": 1000 * (percentile(jitter, 99) or 0.0),
    }


def alone(seconds: float, units: int = UNITS, bare: bool = True) -> dict[str, float]:
    """One run in a fresh namespace: the supervisor, then (``bare``) the bare host, on one
    simulator."""
    return alone_runs(seconds, 1, units, bare)[0]


def window_order(runs: int, bare: bool, interleave: bool) -> list[bool]:
    """Which window comes when: True the supervisor's, False the bare host's."""
    if not bare:
        return [True] * runs
    return [True, False] * runs if interleave else [True] * runs + [False] * runs


def alone_runs(
    seconds: float, runs: int, units: int = UNITS, bare: bool = True, interleave: bool = True
) -> list[dict[str, float]]:
    """``runs`` runs in one fresh namespace, on one simulator: the supervisor's windows and
    (``bare``) the bare host's, alternating (``interleave``: sup, bare, sup, bare …, so
    that each run's pair shares the machine's mood of the moment) or all of the
    supervisor's first. Each run's figures, in order."""
    order = window_order(runs, bare, interleave)
    with tempfile.TemporaryDirectory(dir="/tmp") as name, netns.Namespace() as ns:
        tmp = Path(name)
        cfg = tmp / "alone.yaml"
        cfg.write_text(config(units, RATE, "udp_multicast"))
        listener = ns.popen(
            [sys.executable, "-m", "benchmarks.alone", "listen"], cwd=ROOT, stdout=subprocess.PIPE
        )
        sim = ns.popen(
            [sys.executable, "-m", "abh3_supervisor", "simulate", str(cfg)],
            cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            if _line(listener, "the listener") != "listening":
                raise RuntimeError("the listener did not start")
            if not _line(sim, "abh3 simulate").startswith("ready: bus b"):
                raise RuntimeError("abh3 simulate did not get its drives ready")
            windows: dict[bool, list[Window]] = {True: [], False: []}
            for supervisor in order:
                windows[supervisor].append(
                    _supervisor_window(ns, cfg, sim.pid, seconds, tmp / "run.log")
                    if supervisor
                    else _bare_window(ns, sim.pid, seconds)
                )
        finally:
            _stop(sim)
            listener.send_signal(signal.SIGTERM)  # it prints what it heard, then ends
            out, _ = listener.communicate(timeout=30)
        wire = Wire([(t, i) for t, i in json.loads(out.splitlines()[-1])], units)
    return [
        _figures(wire, ours, host)
        for ours, host in itertools.zip_longest(windows[True], windows[False])
    ]


def _figures(wire: Wire, ours: Window, host: Window | None) -> dict[str, float]:
    n_ours = wire.exchanges(ours)
    n_bare = wire.exchanges(host) if host is not None else None
    if not n_ours or n_bare == 0:
        raise RuntimeError(f"no exchanges heard (supervisor {n_ours}, bare host {n_bare})")
    figures = {
        "ours_us": 1e6 * ours.cpu["supervisor"] / n_ours,
        "simulator_us": 1e6 * ours.cpu["simulator"] / n_ours,
        "ours_cpu_percent": 100 * ours.cpu["supervisor"] / (ours.end - ours.start),
        **wire.timing(ours),
    }
    if host is not None and n_bare:
        figures["bare_us"] = 1e6 * host.cpu["bare"] / n_bare
        figures["ratio"] = figures["ours_us"] / figures["bare_us"]
    return figures


def in_process(seconds: float, units: int = UNITS, timed: bool = True) -> dict[str, float]:
    """The same ``abh3 run`` with its drives in-process: its CPU without a recording, then
    (``timed``) its timing from a second run's ``--record`` (as section 3 times the pump's
    sends)."""
    with tempfile.TemporaryDirectory(dir="/tmp") as name:
        tmp = Path(name)
        cfg = tmp / "inproc.yaml"
        cfg.write_text(config(units, RATE, "virtual"))
        window = _supervisor_window(None, cfg, None, seconds, tmp / "cpu.log")
        cpu = {"cpu_percent": 100 * window.cpu["supervisor"] / (window.end - window.start)}
        if not timed:
            return cpu
        rec = tmp / "timing.log"
        argv = [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless",
                "--no-socket", "--status-interval", "0", "--record", str(rec),
                "--duration", f"{WARMUP_S + seconds + 1:g}"]  # fmt: skip
        subprocess.run(argv, cwd=ROOT, check=True, capture_output=True)
        by_unit: dict[int, list[float]] = defaultdict(list)
        commands = {ids.dp0_command_id(i + 1, HOST): i for i in range(units)}
        sent = [m for m in can.LogReader(str(rec)) if m.arbitration_id in commands]
        start = sent[0].timestamp + WARMUP_S if sent else 0.0
        end = start + seconds  # well before the stop frames
        for msg in sent:
            if start <= msg.timestamp <= end:
                by_unit[commands[msg.arbitration_id]].append(msg.timestamp)
    return cpu | timing(by_unit, RATE, units)


def _spread(values: list[float], unit: str) -> str:
    if len(values) < 2:
        return "1 run" + (f" {values[0]:.3g}{unit}" if unit == "x" and values else "")
    sep = "" if unit == "x" else " "
    return f"runs {min(values):.3g}–{max(values):.3g}{sep}{unit}".rstrip()


SIZING_UNITS = 16  # section 4's sizing row, with the drives elsewhere


def rows(seconds: float, runs: int, sizing: bool = True, interleave: bool = True) -> list[Row]:
    """The section's rows; none (and a line saying why) where no namespace can be made.
    ``sizing``: also the CPU of 16 units, the row a small computer is chosen by;
    ``interleave``: see :func:`alone_runs`."""
    if (why := netns.unavailable()) is not None:
        print(f"section 10 skipped: {why}")
        return []
    ran = alone_runs(seconds, runs, interleave=interleave)
    base = [in_process(seconds) for _ in range(runs)]

    def row(figure: str, key: str, unit: str, baseline: str | float | None,
            target: str = "", ok: Callable[[float], bool] | None = None) -> Row:  # fmt: skip
        """``baseline``: a figure, or the key of the in-process runs' figure."""
        values = [r[key] for r in ran]
        median = statistics.median(values)
        said = _spread(values, unit)
        if isinstance(baseline, str):
            of_base = [r[baseline] for r in base]
            baseline = statistics.median(of_base)
            if runs > 1:
                said += f"; baseline {_spread(of_base, unit)}"
        said = f"{target}; {said}" if target else said
        return Row(SECTION, figure, median, baseline, unit, said, ok(median) if ok else None)

    bare = statistics.median(r["bare_us"] for r in ran)
    ours = statistics.median(r["ours_us"] for r in ran)
    ratios = [r["ratio"] for r in ran]
    n = f"{UNITS} units @{RATE:g} Hz"
    paired = "each run's pair" if interleave else "runs in order"
    # the target holds in every run: each run's ratio, its supervisor and bare host windows
    # side by side (interleaved), not only the ratio of the medians
    return [
        Row(SECTION, f"{n}: CPU per DP0 exchange vs bare host", ours, bare, "us",
            f"<=1.25x every run; {paired} {_spread(ratios, 'x')}; ours "
            f"{_spread([r['ours_us'] for r in ran], 'us')}", max(ratios) <= 1.25),
        Row(SECTION, "bare python-can host: CPU per DP0 exchange", bare, None, "us",
            _spread([r["bare_us"] for r in ran], "us")),
        row("simulator process: CPU per exchange vs supervisor", "simulator_us", "us", ours),
        row("supervisor CPU % of one core vs drives in-process", "ours_cpu_percent", "%",
            "cpu_percent"),
        row("worst unit's rate error vs drives in-process", "rate_error_percent", "%",
            "rate_error_percent", "<=1%", lambda v: v <= 1),
        row("DP0 period jitter p99 vs drives in-process", "jitter_p99_ms", "ms",
            "jitter_p99_ms"),
    ] + (_sizing(seconds, runs) if sizing else [])  # fmt: skip


def _sizing(seconds: float, runs: int) -> list[Row]:
    ran = alone_runs(seconds, runs, SIZING_UNITS, bare=False)
    base = [in_process(seconds, SIZING_UNITS, timed=False) for _ in range(runs)]
    ours, of_base = [r["ours_cpu_percent"] for r in ran], [r["cpu_percent"] for r in base]
    said = _spread(ours, "%") + (f"; baseline {_spread(of_base, '%')}" if runs > 1 else "")
    errors = [r["rate_error_percent"] for r in ran]
    error = statistics.median(errors)
    return [
        Row(SECTION, f"{SIZING_UNITS} units: supervisor CPU % vs drives in-process",
            statistics.median(ours), statistics.median(of_base), "%", said),
        Row(SECTION, f"{SIZING_UNITS} units: worst unit's rate error", error, None, "%",
            f"<=1%; {_spread(errors, '%')}", error <= 1),
    ]  # fmt: skip


# --- the roles run inside the namespace -------------------------------------------------


class _Stopping:
    """SIGTERM ends the role's loop (checked between frames)."""

    def __init__(self) -> None:
        self.now = False
        signal.signal(signal.SIGTERM, self._set)

    def _set(self, signum: int, frame: object) -> None:
        self.now = True


def listen() -> None:
    """Every DP0 frame heard (kernel timestamp, id), as one JSON line at SIGTERM."""
    stopping = _Stopping()
    bus = can.Bus(interface="udp_multicast", channel=CHANNEL)
    print("listening", flush=True)
    heard: list[tuple[float, int]] = []
    while not stopping.now:
        msg = bus.recv(0.1)
        if msg is not None and (msg.arbitration_id >> 16) & 0xFF == ids.PF_SINGLE:
            heard.append((msg.timestamp, msg.arbitration_id))
    bus.shutdown()
    print(json.dumps(heard), flush=True)


def bare(units: int, rate: float) -> None:
    """Every period, for each drive: build a DP0 command, send it, recv until its reply."""
    stopping = _Stopping()
    bus = can.Bus(interface="udp_multicast", channel=CHANNEL)
    # our copies dropped in the kernel, as the supervisor's (simulator/multicast.py)
    sender, in_kernel = own_sender(bus, CHANNEL)
    if not in_kernel:
        print("our own frames cannot be dropped in the kernel here", flush=True)
        return
    started = False
    period = 1.0 / rate
    due = time.monotonic()
    while not stopping.now:
        for abh3 in range(1, units + 1):
            data = frames.encode_dp0_command(0, 0, 0)
            cmd = can.Message(
                arbitration_id=ids.dp0_command_id(abh3, HOST), data=data, is_extended_id=True
            )
            sender.send(pack_message(cmd))  # python-can's packing, as its own send
            reply = ids.dp0_reply_id(abh3, HOST)
            while (msg := bus.recv(0.1)) is not None and msg.arbitration_id != reply:
                pass  # another drive's late reply
            if msg is not None and not started:
                started = True
                print("started", flush=True)
        due += period
        if (delay := due - time.monotonic()) > 0:
            time.sleep(delay)
        else:  # behind: from now on, no burst to catch up
            due = time.monotonic()
    sender.close()
    bus.shutdown()


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.alone [--seconds S] [--runs N] [--no-interleave]``: this
    section only (a board's figures); the roles below are what it starts inside the
    namespace."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.alone", description=__doc__)
    p.add_argument("--seconds", type=float, default=10.0, help="each measuring window")
    p.add_argument("--runs", type=int, default=3, help="repetitions; the median is printed")
    p.add_argument(
        "--interleave",
        action="store_true",
        default=True,
        help="alternate the supervisor's and the bare host's windows (sup, bare, sup, "
        "bare …): the default",
    )
    p.add_argument(
        "--no-interleave",
        dest="interleave",
        action="store_false",
        help="every supervisor window first, then every bare host's",
    )
    sub = p.add_subparsers(dest="role")
    sub.add_parser("listen", help="print the DP0 frames heard, at SIGTERM")
    b = sub.add_parser("bare", help="a bare python-can host, until SIGTERM")
    b.add_argument("--units", type=int, default=UNITS)
    b.add_argument("--rate", type=float, default=RATE)
    a = p.parse_args(argv)
    if a.role == "listen":
        listen()
    elif a.role == "bare":
        bare(a.units, a.rate)
    else:
        print(f"machine: {machine()}")
        print_rows(rows(a.seconds, a.runs, interleave=a.interleave))


if __name__ == "__main__":
    main()
