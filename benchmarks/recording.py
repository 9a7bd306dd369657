"""11. What an ``.mcap`` recording costs, against a ``.log`` of the same run.

One fresh process per run: ``run_headless`` (what ``abh3 run --headless`` runs), 4 units
at 100 Hz on a virtual bus with their simulated drives in the process, every status packet
at 10 Hz, recording to ``.log`` or ``.mcap``; runs interleaved (log, mcap, log, mcap …) so
that a busy machine weighs on both alike. The figure is the **bus loop thread's** CPU time
(``time.thread_time()``, the kernel's per-thread clock, read by callbacks on the loop
itself) over a window after a warm-up, as % of one core: python-can's reader threads and
the process's other threads are not in it; the simulated drives, which run on the loop,
are, in both runs. The ratio is taken per frame on the bus (every frame is recorded), so
that a run the machine starved of its rate does not look cheap. The recording is written
by a thread of its own (runtime/recorder.py): the target is taken on the **whole
process's** CPU per frame (``time.process_time()``, every thread), the loop's own beside
it. Printed: the medians, the median of the pairs' ratios and their spread, and the
recorder's calls' share of the loop's CPU: the same clock read around each of them
(frames, events, flushes), in the same runs.

``python -m benchmarks.recording [--runs N] [--seconds S]`` prints this section alone.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib.util
import json
import logging
import statistics
import subprocess
import sys
import tempfile
import time
import timeit
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from benchmarks.report import Row, machine, print_rows

ROOT = Path(__file__).resolve().parent.parent
UNITS, RATE = 4, 100.0
WARMUP_S = 2.0  # start-up (the drives' settings read) done, the loop settled
SECTION = "11. recording: CPU, .mcap vs .log (4 units @100 Hz, in-process sims)"


def config(channel: str) -> str:
    units = "".join(
        f"  - {{name: u{i}, abh3_id: {i + 1}, host_id: 100, command_rate_hz: {RATE:g}, "
        f"broadcast: {{mask: 0x7F, rate_hz: 10}}}}\n"
        for i in range(UNITS)
    )
    return (
        f"buses:\n  b: {{interface: virtual, channel: {channel}, simulate: true}}\nunits:\n{units}"
    )


@dataclass(frozen=True)
class Run:
    loop_cpu: float  # % of one core
    recorder_cpu: float  # % of one core, the recorder's calls on the loop
    frames_per_s: float  # on the bus, sent and received (every one recorded)
    process_cpu: float  # % of one core, every thread (the recorder's writer too)

    @property
    def us_per_frame(self) -> float:
        """The loop's CPU per frame on the bus: as the CPU, but not lowered by a run the
        machine starved of its rate."""
        return 1e4 * self.loop_cpu / self.frames_per_s

    @property
    def process_us_per_frame(self) -> float:
        """The whole process's CPU per frame on the bus."""
        return 1e4 * self.process_cpu / self.frames_per_s


def _timed(spent: list[float], method: Callable[..., None], frame: bool) -> Callable[..., None]:
    def timed(self: object, *args: object) -> None:
        start = time.thread_time()
        try:
            method(self, *args)
        finally:
            spent[0] += time.thread_time() - start
            spent[1] += frame

    return timed


async def _measure(record: Path, seconds: float) -> dict[str, float]:
    from abh3_supervisor.config import parse_config
    from abh3_supervisor.runtime.headless import run_headless
    from abh3_supervisor.runtime.recorder import GuardedRecorder

    loop = asyncio.get_running_loop()
    marks: list[tuple[float, float, float, float, float]] = []
    spent = [0.0, 0.0]  # the recorder's CPU on the loop, frames recorded
    for name in ("on_message_received", "observe", "flush"):
        method = getattr(GuardedRecorder, name)
        setattr(GuardedRecorder, name, _timed(spent, method, name == "on_message_received"))

    def mark() -> None:  # on the loop thread: its own CPU clock
        marks.append((loop.time(), time.thread_time(), spent[0], spent[1], time.process_time()))

    loop.call_later(WARMUP_S, mark)
    loop.call_later(WARMUP_S + seconds, mark)
    cfg = parse_config(config(f"rec-{record.suffix[1:]}"), "recording.yaml")
    code = await run_headless(
        cfg, duration=WARMUP_S + seconds + 0.5, record=record, status_interval=0
    )
    (t0, cpu0, rec0, n0, all0), (t1, cpu1, rec1, n1, all1) = marks
    return {
        "process_cpu_percent": 100 * (all1 - all0) / (t1 - t0),
        "code": code,
        "loop_cpu_percent": 100 * (cpu1 - cpu0) / (t1 - t0),
        "recorder_cpu_percent": 100 * (rec1 - rec0) / (t1 - t0),
        "frames_per_s": (n1 - n0) / (t1 - t0),
    }


def child(suffix: str, seconds: float) -> None:
    """One run, in this (fresh) process: its figures as JSON on stdout."""
    logging.disable(logging.WARNING)
    with tempfile.TemporaryDirectory(prefix="abh3-rec-") as tmp:
        figures = asyncio.run(_measure(Path(tmp) / f"run{suffix}", seconds))
    print(json.dumps(figures))


def one(suffix: str, seconds: float) -> Run:
    """One run recording to ``suffix``, in a process of its own."""
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.recording", "--child", suffix, "--seconds",
         f"{seconds:g}"],
        cwd=ROOT, capture_output=True, text=True, check=True, timeout=seconds + 120,
    )  # fmt: skip
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    if figures["code"] != 0:
        raise RuntimeError(f"the {suffix} run ended with exit code {figures['code']}")
    return Run(
        figures["loop_cpu_percent"],
        figures["recorder_cpu_percent"],
        figures["frames_per_s"],
        figures["process_cpu_percent"],
    )


def pairs(seconds: float, runs: int) -> list[tuple[Run, Run]]:
    """.log's and .mcap's figures (:func:`one`) in ``runs`` interleaved pairs."""
    return [(one(".log", seconds), one(".mcap", seconds)) for _ in range(runs)]


def encode_us(n: int = 20_000) -> tuple[float, float | None]:
    """µs to encode one ``can_msgs/Frame``: ours (runtime/cdr.py), and mcap_ros2's dynamic
    encoder on the message as a dict (what the recording did before), if installed."""
    from abh3_supervisor.runtime.cdr import frame_encoder
    from abh3_supervisor.runtime.ros_topics import FRAME, SCHEMAS

    msg = can.Message(arbitration_id=0x00C0_0101, data=bytes(8), timestamp=1.7e9)
    encode = frame_encoder("b")

    def ours() -> bytes:
        sec, nanosec = divmod(int(msg.timestamp * 1e9), 1_000_000_000)
        return encode(sec, nanosec, msg.arbitration_id, False, True, False, 8, msg.data)

    ours_us = min(timeit.repeat(ours, number=n, repeat=3)) / n * 1e6
    if importlib.util.find_spec("mcap_ros2") is None:
        return ours_us, None
    from mcap_ros2._dynamic import serialize_dynamic

    dynamic = serialize_dynamic(FRAME, SCHEMAS[FRAME])[FRAME]

    def before() -> bytes:
        ns = int(msg.timestamp * 1e9)
        return dynamic(
            {
                "header": {"stamp": {"sec": ns // 10**9, "nanosec": ns % 10**9}, "frame_id": "b"},
                "id": msg.arbitration_id,
                "is_rtr": False,
                "is_extended": True,
                "is_error": False,
                "dlc": 8,
                "data": list(msg.data),
            }
        )

    return ours_us, min(timeit.repeat(before, number=n // 10, repeat=3)) / (n // 10) * 1e6


def rows(seconds: float, runs: int) -> list[Row]:
    if importlib.util.find_spec("mcap") is None:
        print("section 11 skipped: pip install -e '.[mcap]' for the recording figures")
        return []
    measured = pairs(seconds, runs)

    def median(figure: Callable[[Run], float], which: int) -> float:
        return statistics.median(figure(pair[which]) for pair in measured)

    ratios = sorted(mcap.us_per_frame / log.us_per_frame for log, mcap in measured)
    ratio = statistics.median(ratios)
    spread = f"{ratios[0]:.2f}–{ratios[-1]:.2f}x" if len(ratios) > 1 else "1 run"
    whole = sorted(mcap.process_us_per_frame / log.process_us_per_frame for log, mcap in measured)
    whole_ratio = statistics.median(whole)
    whole_spread = f"{whole[0]:.2f}–{whole[-1]:.2f}x" if len(whole) > 1 else "1 run"
    ours_us, before_us = encode_us()

    def row(figure: str, value: Callable[[Run], float], unit: str) -> Row:
        return Row(SECTION, f"{figure}: .mcap vs .log", median(value, 1), median(value, 0), unit)

    return [
        row("loop thread CPU, % of one core", lambda r: r.loop_cpu, "%"),
        row("frames on the bus (every one recorded)", lambda r: r.frames_per_s, "/s"),
        row("loop thread CPU per frame", lambda r: r.us_per_frame, "us"),
        Row(
            SECTION,
            f"pairs' ratio of that, median of {len(ratios)} ({spread})",
            ratio,
            1.0,
            "x",
        ),
        row("process CPU per frame (every thread)", lambda r: r.process_us_per_frame, "us"),
        Row(
            SECTION,
            f"pairs' ratio of that, median of {len(whole)} ({whole_spread})",
            whole_ratio,
            1.0,
            "x",
            "<=1.10x",
            whole_ratio <= 1.10,
        ),
        row("the recorder's own share of the loop", lambda r: r.recorder_cpu, "%"),
        Row(
            SECTION,
            "encode a can_msgs/Frame: struct vs mcap_ros2 dynamic",
            ours_us,
            before_us,
            "us",
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.recording", description=__doc__)
    p.add_argument("--runs", type=int, default=5, help="interleaved pairs (default 5)")
    p.add_argument("--seconds", type=float, default=10.0, help="measured window per run")
    p.add_argument("--child", metavar="SUFFIX", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        child(a.child, a.seconds)
        return 0
    print(f"machine: {machine()}")
    print_rows(rows(a.seconds, a.runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
