"""3b. Everything on, as an operator runs it: one headless supervisor process (8 simulated
units at 100 Hz, the ROS 2 bridge publishing on loopback, an MCAP recording), then two
real ``abh3 tui --connect`` in tmux (one on the plots tab) attached halfway through.

The DP0 period jitter is read from the run's own recording — the time each command frame
left the host — in the window before the TUIs attach ("alone") and in the window while
they are attached, so both figures come from one run on one machine state. Without tmux
the TUIs run headless from ``benchmarks.tui_client`` instead (said in the row's label).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import can

from abh3_supervisor.protocol import ids
from abh3_supervisor.runtime.mcap_recording import read_frames
from abh3_supervisor.scheduler.stats import percentile

ROOT = Path(__file__).resolve().parent.parent
HOST = 100
DOMAIN = 77
UNITS, RATE = 8, 100.0
SETTLE_S = 2.0  # after a start or an attach: the first screens, discovery


def config(channel: str, ros: bool, units: int = UNITS, csv: Path | None = None) -> str:
    listed = "".join(
        f"  - {{name: u{i}, bus: b, abh3_id: {i + 1}, host_id: {HOST}, "
        f"command_rate_hz: {RATE:g}, broadcast: {{mask: 0x7F, rate_hz: 10}}}}\n"
        for i in range(units)
    )
    text = f"buses:\n  b: {{interface: virtual, channel: {channel}, simulate: true}}\n"
    text += f"units:\n{listed}"
    plugins = [f"ros2: {{domain_id: {DOMAIN}, transport: dds}}"] if ros else []
    plugins += [f"csv: {{path: {csv}}}"] if csv is not None else []
    if plugins:
        text += f"plugins: {{{', '.join(plugins)}}}\n"
    return text


@contextlib.contextmanager
def supervisor(
    tmp: Path, text: str, record: Path, seconds: float
) -> Iterator[tuple[subprocess.Popen[bytes], Path]]:
    """``abh3 run`` headless on ``text`` for at most ``seconds``: the process and its
    socket, once it serves it. Stopped (SIGTERM: drives stopped, files closed) after."""
    cfg, sock = tmp / "bench.yaml", tmp / "s" / "bench.sock"
    cfg.write_text(text)
    sup = subprocess.Popen(
        [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless",
         "--socket", str(sock), "--record", str(record), "--duration", f"{seconds:g}"],
        cwd=ROOT, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not sock.exists():
            if sup.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the supervisor did not serve its socket")
            time.sleep(0.05)
        yield sup, sock
    finally:
        sup.terminate()
        sup.wait(30)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    with contextlib.suppress(ImportError):
        from abh3_plugins.ros2.dds import LOOPBACK_URI  # the bridge on loopback only

        env["CYCLONEDDS_URI"] = LOOPBACK_URI
    return env


@contextlib.contextmanager
def _tuis(sock: Path, n: int, tmp: Path) -> Iterator[str]:
    """``n`` TUIs attached to ``sock``, the first on the plots tab; yields how."""
    abh3 = [sys.executable, "-m", "abh3_supervisor"]
    if shutil.which("tmux"):
        server = ["tmux", "-S", str(tmp / "tmux.sock")]
        cmd = " ".join([*abh3, "tui", "--connect", str(sock)])
        first = ["new-session", "-d", "-x", "160", "-y", "50", "-s", "b", cmd]
        for args in [first, *(["new-window", "-d", "-t", "b:", cmd] for _ in range(n - 1))]:
            subprocess.run([*server, *args], check=True, cwd=ROOT, env=_env())
        time.sleep(SETTLE_S)  # attached and drawn (a benchmark, not a test)
        subprocess.run([*server, "send-keys", "-t", "b:0", "5"], check=True)
        try:
            yield "tmux"
        finally:
            subprocess.run([*server, "kill-server"], check=False)
        return
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "benchmarks.tui_client", str(sock), "3600"], cwd=ROOT
        )
        for _ in range(n)
    ]
    try:
        time.sleep(SETTLE_S)
        yield "headless Textual"
    finally:
        for p in procs:
            p.terminate()
            p.wait(10)


def _jitter(times_by_unit: dict[int, list[float]], start: float, end: float) -> dict[str, float]:
    period = 1.0 / RATE
    jitter: list[float] = []
    rates: list[float] = []
    for times in times_by_unit.values():
        window = [t for t in times if start <= t <= end]
        jitter += [abs((b - a) - period) for a, b in itertools.pairwise(window)]
        if len(window) > 1:
            rates.append((len(window) - 1) / (window[-1] - window[0]))
    return {
        "jitter_p99_ms": 1000 * (percentile(jitter, 99) or 0.0),
        "jitter_p50_ms": 1000 * (percentile(jitter, 50) or 0.0),
        "rate_error_percent": 100 * max(abs(r - RATE) / RATE for r in rates),
    }


def _frames(path: Path) -> Iterator[can.Message]:
    if path.suffix == ".mcap":
        yield from read_frames(path, lambda line: None)
    else:
        yield from can.LogReader(str(path))


def run(
    seconds: float, tuis: int = 2, ros: bool = True, record: str = "mcap"
) -> tuple[str, dict[str, float]]:
    """Alone for ``seconds``, then ``tuis`` attached for ``seconds``; figures per window."""
    with tempfile.TemporaryDirectory(dir="/tmp") as name:
        tmp = Path(name)
        rec = tmp / f"run.{record}"
        total = 2 * (seconds + SETTLE_S) + 4 * SETTLE_S
        with supervisor(tmp, config(f"attached-{os.getpid()}", ros), rec, total) as (_, sock):
            time.sleep(SETTLE_S)
            alone = (time.time(), time.time() + seconds)
            time.sleep(seconds)
            with _tuis(sock, tuis, tmp) as how:
                attached = (time.time(), time.time() + seconds)
                time.sleep(seconds)
        times: dict[int, list[float]] = defaultdict(list)
        wanted = {ids.dp0_command_id(i + 1, HOST) for i in range(UNITS)}
        for msg in _frames(rec):
            if msg.arbitration_id in wanted:
                times[msg.arbitration_id].append(msg.timestamp)
    a, b = _jitter(times, *alone), _jitter(times, *attached)
    return how, {
        **{f"alone_{k}": v for k, v in a.items()},
        **{f"attached_{k}": v for k, v in b.items()},
    }


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


def memory(seconds: float, warmup: float = 30.0, units: int = 4) -> dict[str, float]:
    """RSS of an everything-on supervisor (``units`` at 100 Hz, the ROS 2 bridge, an MCAP
    recording, the CSV plugin, one TUI on the plots tab) from ``warmup`` to the end."""
    with tempfile.TemporaryDirectory(dir="/tmp") as name:
        tmp = Path(name)
        text = config(f"memory-{os.getpid()}", True, units, csv=tmp / "out.csv")
        total = warmup + seconds + 4 * SETTLE_S
        with contextlib.ExitStack() as stack:
            sup, sock = stack.enter_context(supervisor(tmp, text, tmp / "run.mcap", total))
            stack.enter_context(_tuis(sock, 1, tmp))
            time.sleep(max(0.0, warmup - SETTLE_S))
            start = _rss_mb(sup.pid)
            samples: list[float] = []
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                time.sleep(min(10.0, max(0.0, end - time.monotonic())))
                samples.append(_rss_mb(sup.pid))
    half = samples[len(samples) // 2 :]
    return {
        "rss_start_mb": start,
        "rss_end_mb": samples[-1],
        "rss_growth_mb": samples[-1] - start,
        "rss_peak_mb": max(samples),
        "late_growth_mb_per_min": 60 * (half[-1] - half[0]) / max(1.0, seconds / 2),
    }


if __name__ == "__main__":  # SECONDS [TUIS [ROS 0|1 [FORMAT mcap|log]]] | memory SECONDS
    a = sys.argv[1:] + [""] * 4
    if a[0] == "memory":
        print(memory(float(a[1] or 60)))
    else:
        print(run(float(a[0] or 10), int(a[1] or 2), a[2] != "0", a[3] or "mcap"))
