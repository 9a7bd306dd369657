"""11. A small computer's budget: the supervisor held to a share of one core.

The supervisor (``abh3 run --headless --priority normal``, an MCAP recording, the ROS 2
bridge publishing over DDS) runs in a CPU cgroup limited to a share of one core of this
machine (:mod:`benchmarks.cgroup`); everything else is outside it: the simulated drives
(``abh3 simulate`` on ``udp_multicast``, in a network namespace whose only interface is
``lo``, as section 10 does: :mod:`benchmarks.alone`), one attached TUI (a headless Textual
client, :mod:`benchmarks.tui_client`) and the wire listener. A configuration *holds* when,
over the measuring window after warm-up,

* every unit's command rate on the wire is within 1 % of the requested one,
* the DP0 command period's jitter p99 (kernel timestamps, on the wire) is ≤ 5 ms, and
* the supervisor counted no reply timeout (its own counters, read over the control socket).

The row of issue 34 is 4 units at 100 Hz on 10 % of one core; the sizing table is the
largest number of units that still holds at each command rate, at 5, 10 and 25 %.
``python -m benchmarks.small`` (or ``python -m benchmarks --small``) prints this section
only, as a board's figures; it needs root (a cgroup) and a network namespace, and says so
where it cannot have them.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from abh3_supervisor.clients.link import Link
from abh3_supervisor.clients.tui.app import STATE_HZ
from abh3_supervisor.config import parse_config
from abh3_supervisor.core import planner
from abh3_supervisor.protocol import ids
from abh3_supervisor.runtime import netns
from benchmarks import alone, cgroup
from benchmarks.report import Row, machine, print_rows

SECTION = (
    "12. a small computer's budget (supervisor in a CPU cgroup with MCAP and the ROS 2 "
    "bridge; the drives and 1 TUI outside)"
)
UNITS, RATE, PERCENT = 4, 100.0, 10.0  # issue 34's row
SHARES = (5.0, 10.0, 25.0)  # % of one core: the sizing table's columns
SIZING_UNITS = (1, 2, 4, 8, 16)
SIZING_RATES = (50.0, 100.0, 200.0)
DOMAIN = 78  # the bridge's DDS domain (section 6 and 3b use 77)
RATE_TOLERANCE, JITTER_P99_MS = 1.0, 5.0  # %, ms: what "holds" means
SIMULATOR_BOUND = 80.0  # % of a core: above it the drives' process, not ours, may fall behind
SETTLE_S = 2.0  # after the TUI attached: its first screens, DDS discovery
START_CPU_S = 6.0  # CPU seconds a start may take (imports, DDS, drive checks): the
# start-up timeout is this over the share, so a 5 % run is given its two minutes


def config(units: int, rate: float, bridge: bool) -> str:
    """The supervisor's file (the simulator reads the same, without the plugin): status
    broadcasts at 10 Hz as a robot reads them, the bridge on DDS in the namespace."""
    listed = "".join(
        f"  - {{name: u{i}, bus: b, abh3_id: {i + 1}, host_id: {alone.HOST}, "
        f"command_rate_hz: {rate:g}, broadcast: {{mask: 0x7F, rate_hz: 10}}}}\n"
        for i in range(units)
    )
    bitrate = 1_000_000 if units * rate > 800 else 500_000  # the planner's bus budget
    bus = (
        f"b: {{interface: udp_multicast, channel: {alone.CHANNEL}, bitrate: {bitrate}, "
        "simulate: true}"
    )
    text = f"buses:\n  {bus}\nunits:\n{listed}"
    if bridge:  # its DDS start on the smallest share takes longer than the 5 s default
        text += (
            f"plugins: {{ros2: {{domain_id: {DOMAIN}, transport: dds, "
            f"start_timeout_s: {START_CPU_S / (min(SHARES) / 100):g}}}}}\n"
        )
    return text


def bridge_available() -> str | None:
    """Why the ROS 2 bridge cannot run here, or None (it needs the ros2 extra)."""
    if importlib.util.find_spec("cyclonedds") is None:
        return "no cyclonedds (pip install -e '.[ros2]')"
    return None


def _env() -> dict[str, str]:
    env = dict(os.environ)
    with contextlib.suppress(ImportError):
        from abh3_plugins.ros2.dds import LOOPBACK_URI  # DDS on loopback (and only lo)

        env["CYCLONEDDS_URI"] = LOOPBACK_URI
    return env


async def _counters(sock: Path) -> dict[str, int]:
    """Reply timeouts per unit, as the supervisor counts them (its ``state``)."""
    link = await Link.open(sock, timeout=30.0)
    try:
        state: dict[str, Any] = await link.call("state")
    finally:
        await link.close()
    return {name: int(unit["stats"]["timeouts"]) for name, unit in state["units"].items()}


@contextlib.contextmanager
def _tui(sock: Path, err: Path, states: Path) -> Iterator[subprocess.Popen[bytes]]:
    """The attached TUI; what it says on stderr goes to ``err``, a line per state it
    applied to ``states`` (benchmarks/tui_client.py)."""
    with err.open("w") as said:
        tui = subprocess.Popen(
            [sys.executable, "-m", "benchmarks.tui_client", str(sock), "3600", str(states)],
            cwd=alone.ROOT, stdout=subprocess.DEVNULL, stderr=said,
        )  # fmt: skip
    try:
        yield tui
    finally:
        tui.terminate()
        try:
            tui.wait(10)
        except subprocess.TimeoutExpired:
            tui.kill()
            tui.wait()


@dataclass
class Run:
    """What one configuration did in its window."""

    units: int
    rate: float
    percent: float
    figures: dict[str, float]  # none if it did not start
    why: str = ""  # why it did not start (a start-up that does not fit the share)

    @property
    def holds(self) -> bool:
        f = self.figures
        return (
            not self.why
            and f["rate_error_percent"] <= RATE_TOLERANCE
            and f["jitter_p99_ms"] <= JITTER_P99_MS
            and f["timeouts"] == 0
        )


def run(
    percent: float,
    units: int = UNITS,
    rate: float = RATE,
    seconds: float = 10.0,
    *,
    bridge: bool = True,
    record: bool = True,
    tui: bool = True,
) -> Run:
    """One configuration in a fresh namespace and cgroup; the figures of its window."""
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(dir="/tmp")))
        ns = stack.enter_context(netns.Namespace())
        limit = stack.enter_context(cgroup.CpuLimit(percent))
        (tmp / "sim.yaml").write_text(config(units, rate, bridge=False))
        (tmp / "run.yaml").write_text(config(units, rate, bridge))
        listener = ns.popen(
            [sys.executable, "-m", "benchmarks.alone", "listen"],
            cwd=alone.ROOT, stdout=subprocess.PIPE,
        )  # fmt: skip
        sim = ns.popen(
            [sys.executable, "-m", "abh3_supervisor", "simulate", str(tmp / "sim.yaml")],
            cwd=alone.ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            if alone._line(listener, "the listener") != "listening":
                raise RuntimeError("the listener did not start")
            if not alone._line(sim, "abh3 simulate").startswith("ready: bus b"):
                raise RuntimeError("abh3 simulate did not get its drives ready")
            window, timeouts, throttled = _supervised(
                ns, limit, tmp, seconds, sim.pid, record=record, tui=tui
            )
            view = _view(tmp / "tui.states", window) if tui else {}
        except NotStarted as exc:
            return Run(units, rate, percent, {}, why=str(exc))
        finally:
            alone._stop(sim)
            listener.terminate()  # it prints what it heard, then ends
            out, _ = listener.communicate(timeout=30)
    wire = alone.Wire([(t, i) for t, i in _heard(out)], units)
    by_unit: dict[int, list[float]] = defaultdict(list)
    commands = {ids.dp0_command_id(i + 1, alone.HOST): i for i in range(units)}
    for t, i in wire.frames:
        if window.start <= t <= window.end and i in commands:
            by_unit[commands[i]].append(t)
    span = window.end - window.start
    figures = {
        **alone.timing(by_unit, rate, units),
        "timeouts": float(timeouts),
        "supervisor_cpu_percent": 100 * window.cpu["supervisor"] / span,
        "simulator_cpu_percent": 100 * window.cpu["simulator"] / span,
        "throttled_percent": 100 * throttled,
        **view,
    }
    return Run(units, rate, percent, figures)


def _view(states: Path, window: alone.Window) -> dict[str, float]:
    """The attached TUI's states in the window: how many a second, and the share of them
    pushed slowed (the view gives way to late buses: service/view_pace.py)."""
    text = states.read_text() if states.exists() else ""  # none: it never got a hello
    lines = [line.split() for line in text.splitlines()]
    seen = [int(by) for t, by in lines if window.start <= float(t) <= window.end]
    return {
        "tui_state_hz": len(seen) / (window.end - window.start),
        "tui_slowed_percent": 100 * sum(by > 1 for by in seen) / len(seen) if seen else 0.0,
    }


class NotStarted(RuntimeError):
    """``abh3 run`` did not get its units running, or its attached TUI gave up within
    the share: the line that says why (the run does not hold)."""


def _said(log: Path) -> str:
    lines = [line for line in log.read_text().splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:")]
    return (errors or lines or ["nothing said"])[-1]


def _heard(out: str) -> list[tuple[float, int]]:
    lines = out.splitlines()
    if not lines:
        raise RuntimeError("the listener said nothing")
    return [(float(t), int(i)) for t, i in json.loads(lines[-1])]


def _supervised(
    ns: netns.Namespace,
    limit: cgroup.CpuLimit,
    tmp: Path,
    seconds: float,
    sim_pid: int,
    *,
    record: bool,
    tui: bool,
) -> tuple[alone.Window, int, float]:
    """``abh3 run`` in the cgroup from its first instruction; the window, the reply
    timeouts counted in it, and the share of its periods the limit throttled."""
    sock, log = tmp / "s" / "run.sock", tmp / "run.err"
    argv = [sys.executable, "-m", "abh3_supervisor", "run", str(tmp / "run.yaml"),
            "--headless", "--priority", "normal", "--status-interval", "0",
            "--socket", str(sock)]  # fmt: skip
    if record:
        argv += ["--record", str(tmp / "run.mcap")]
    with log.open("w") as err:
        sup = subprocess.Popen(
            ns.command(argv), text=True, cwd=alone.ROOT, env=_env(),
            stdout=subprocess.DEVNULL, stderr=err, preexec_fn=limit.enter,
        )  # fmt: skip
    try:
        started = time.monotonic()
        deadline = started + START_CPU_S / (limit.percent / 100)
        while not (sock.exists() and "running " in log.read_text()):
            if sup.poll() is not None:
                raise NotStarted(f"exit {sup.returncode}, {_said(log)}")
            if time.monotonic() > deadline:
                raise NotStarted(f"not running within {deadline - started:.0f} s, {_said(log)}")
            time.sleep(0.05)
        tui_err = tmp / "tui.err"
        tui_states = tmp / "tui.states"
        with _tui(sock, tui_err, tui_states) if tui else contextlib.nullcontext() as attached:
            time.sleep(SETTLE_S + alone.WARMUP_S)  # attached, drawn, discovered
            before, held = asyncio.run(_counters(sock)), limit.throttled()
            window = alone._measure({"supervisor": sup.pid, "simulator": sim_pid}, seconds)
            after, held_after = asyncio.run(_counters(sock)), limit.throttled()
            if sup.poll() is not None:
                raise RuntimeError(f"abh3 run ended during the window:\n{log.read_text()}")
            if attached is not None and attached.poll() is not None:
                # an operator's TUI that cannot stay attached: the share does not carry it
                raise NotStarted(f"the attached TUI ended during the window: {_said(tui_err)}")
    finally:
        alone._stop(sup)
    timeouts = sum(after[name] - before.get(name, 0) for name in after)
    periods = held_after["periods"] - held["periods"]
    throttled = (held_after["throttled"] - held["throttled"]) / periods if periods else 0.0
    return window, timeouts, throttled


# --- the rows ---------------------------------------------------------------------------


def rows(
    seconds: float, runs: int, sizing: bool = True, shares: Sequence[float] = SHARES
) -> list[Row]:
    """The section's rows; none (and a line saying why) where no cgroup or namespace
    can be made. ``sizing``: also what each part costs, and the largest configuration
    that holds at each of ``shares`` (% of one core)."""
    why = cgroup.unavailable() or netns.unavailable()
    if why is not None:
        print(f"section 12 skipped: {why}")
        return []
    no_bridge = bridge_available()
    if no_bridge is not None:
        print(f"section 12: without the ROS 2 bridge ({no_bridge})")
    bridge = no_bridge is None
    # the row and its baseline (the same run given a whole core) interleaved, so a noisy
    # machine moves both
    ran: list[Run] = []
    base: list[Run] = []
    for _ in range(runs):
        ran.append(run(PERCENT, seconds=seconds, bridge=bridge))
        base.append(run(100.0, seconds=seconds, bridge=bridge))
    n = f"{PERCENT:g} % of a core, {UNITS} units @{RATE:g} Hz" + ("" if bridge else " NO bridge")
    out = [
        _row(ran, base, f"{n}: worst rate error", "rate_error_percent", "%",
             f"<={RATE_TOLERANCE:g}%", lambda v: v <= RATE_TOLERANCE),
        _row(ran, base, "  DP0 period jitter p99 (baseline: a whole core)", "jitter_p99_ms",
             "ms", f"<={JITTER_P99_MS:g} ms", lambda v: v <= JITTER_P99_MS),
        _row(ran, base, "  reply timeouts in the window", "timeouts", "", "0",
             lambda v: v == 0),
        _row(ran, base, "  supervisor CPU % of one core", "supervisor_cpu_percent", "%"),
        _row(ran, base, "  periods the limit held it back", "throttled_percent", "%"),
        _row(ran, base, f"  the TUI's states /s (asked: {STATE_HZ:g}; fewer: slowed)",
             "tui_state_hz", "/s"),
        _row(ran, base, "  the TUI's states pushed slowed", "tui_slowed_percent", "%"),
        _row(ran, base, "  the simulator's CPU % (outside the limit)",
             "simulator_cpu_percent", "%"),
    ]  # fmt: skip
    if sizing:
        out += breakdown_rows(seconds, runs, bridge)
        out += sizing_rows(seconds, runs, bridge, shares)
    return out


def _row(
    ran: list[Run],
    base: list[Run],
    figure: str,
    key: str,
    unit: str,
    target: str = "",
    ok: Callable[[float], bool] | None = None,
) -> Row:
    values = [r.figures[key] for r in ran if not r.why]
    of_base = [r.figures[key] for r in base if not r.why]
    baseline = statistics.median(of_base) if of_base else None
    if not values:
        why = next(r.why for r in ran if r.why)
        return Row(SECTION, figure, 0.0, baseline, unit, f"did not start: {why}", False)
    median = statistics.median(values)
    said = alone._spread(values, unit)
    if (missed := len(ran) - len(values)) > 0:
        said += f" ({missed} did not start)"
    if len(of_base) > 1:
        said += f"; baseline {alone._spread(of_base, unit)}"
    said = f"{target}; {said}" if target else said
    return Row(SECTION, figure, median, baseline, unit, said, ok(median) if ok else None)


PARTS = (  # what each part of the row costs: (label, record, bridge, TUI), cumulative
    (f"{UNITS} units @{RATE:g} Hz headless", False, False, False),
    ("+ MCAP recording", True, False, False),
    ("+ ROS 2 bridge", True, True, False),
    ("+ 1 TUI attached", True, True, True),
)


def breakdown(seconds: float, runs: int, bridge: bool) -> dict[str, list[float]]:
    """The supervisor's CPU % given a whole core, part by part (repetitions interleaved:
    every part once, then again)."""
    parts = [p for p in PARTS if bridge or not p[2]]
    cpu: dict[str, list[float]] = {label: [] for label, *_ in parts}
    for _ in range(runs):
        for label, record, bridged, tui in parts:
            done = run(100.0, seconds=seconds, bridge=bridged, record=record, tui=tui)
            if not done.why:  # a whole core starts it: else a fault, said in its row
                cpu[label].append(done.figures["supervisor_cpu_percent"])
    return cpu


def breakdown_rows(seconds: float, runs: int, bridge: bool) -> list[Row]:
    """Each part's CPU against the one before it: what a board pays for each."""
    out = []
    before: float | None = None
    for label, values in breakdown(seconds, runs, bridge).items():
        if not values:
            out.append(Row(SECTION, f"a whole core: {label}", 0.0, None, "", "did not start"))
            continue
        median = statistics.median(values)
        figure = f"a whole core, CPU %: {label}"
        out.append(Row(SECTION, figure, median, before, "%", alone._spread(values, "%")))
        before = median
    return out


def largest(holds: Callable[[int], bool], counts: Sequence[int]) -> int:
    """The largest of ``counts`` (ascending) for which ``holds``, by bisection (holding
    is taken as monotonic: fewer units never cost more); 0 if none does."""
    lo, hi = -1, len(counts)  # counts[lo] holds, counts[hi] does not (lo = -1: none known)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if holds(counts[mid]):
            lo = mid
        else:
            hi = mid
    return counts[lo] if lo >= 0 else 0


def fits(units: int, rate: float) -> bool:
    """Whether the configuration fits a CAN bus at all (``abh3 run`` refuses one whose
    worst case exceeds it: core/planner.py): no computer is sized for the others."""
    cfg = parse_config(config(units, rate, bridge=False), "small.yaml")
    return all(p.worst_load_percent <= 100 for p in planner.plan(cfg))


@dataclass
class Size:
    """The largest count that held at one (share, rate), and the first that did not."""

    units: int
    failed: Run | None  # the smallest count tried that did not hold, if any


def median_run(runs: Sequence[Run]) -> Run:
    """Repetitions of one configuration as one: the median of each figure."""
    first, started = runs[0], [r for r in runs if not r.why]
    if 2 * len(started) <= len(runs):  # most did not start: it does not
        why = next(r.why for r in runs if r.why)
        return Run(first.units, first.rate, first.percent, {}, why=why)
    keys = started[0].figures
    figures = {key: statistics.median(r.figures[key] for r in started) for key in keys}
    return Run(first.units, first.rate, first.percent, figures)


def sizing(
    seconds: float, bridge: bool, runs: int = 1, shares: Sequence[float] = SHARES
) -> dict[tuple[float, float], Size]:
    """The largest number of units that holds at each (share, rate), by bisection; a
    count holds when the median of ``runs`` repetitions does (a noisy machine)."""
    found: dict[tuple[float, float], Size] = {}
    for percent in shares:
        for rate in SIZING_RATES:
            failed: list[Run] = []

            def holds(
                units: int, percent: float = percent, rate: float = rate, failed: list[Run] = failed
            ) -> bool:
                done = median_run(
                    [run(percent, units, rate, seconds, bridge=bridge) for _ in range(runs)]
                )
                verdict = "holds" if done.holds else "does not hold"
                print(f"section 12: {units} @{rate:g} Hz on {percent:g} %: {verdict}", flush=True)
                if not done.holds:
                    failed.append(done)
                return done.holds

            counts = [n for n in SIZING_UNITS if fits(n, rate)]
            units = largest(holds, counts)
            first = min(failed, key=lambda r: r.units) if failed else None
            found[percent, rate] = Size(units, first)
    return found


def sizing_rows(
    seconds: float, runs: int, bridge: bool, shares: Sequence[float] = SHARES
) -> list[Row]:
    out = []
    for (percent, rate), size in sizing(seconds, bridge, runs, shares).items():
        said = f"{size.units * rate:g} commands/s"
        if (f := size.failed) is not None and f.why:
            said += f"; {f.units} did not start: {f.why}"
        elif f is not None:
            said += (
                f"; {f.units} did not: rate error {f.figures['rate_error_percent']:.2g} %, "
                f"p99 {f.figures['jitter_p99_ms']:.2g} ms, "
                f"{f.figures['timeouts']:g} timeouts"
            )
            if f.figures["simulator_cpu_percent"] >= SIMULATOR_BOUND:
                said += f" (the simulator at {f.figures['simulator_cpu_percent']:.0f} %)"
        else:
            said += "; every count the bus carries held"
        out.append(
            Row(SECTION, f"largest that holds at {percent:g} % of a core, {rate:g} Hz",
                float(size.units), None, "units", said)
        )  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.small [--seconds S] [--runs N] [--shares P …] [--quick | --row]``."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.small", description=__doc__)
    p.add_argument("--seconds", type=float, default=10.0, help="each measuring window")
    p.add_argument("--runs", type=int, default=3, help="repetitions; the median is printed")
    p.add_argument(
        "--shares",
        type=float,
        nargs="+",
        default=list(SHARES),
        help="%% of one core the sizing table is taken at (on a board: 25 50 100)",
    )
    p.add_argument("--quick", action="store_true", help="one short run, no sizing table")
    p.add_argument(
        "--row", action="store_true", help="issue 34's row and its baseline only (--runs each)"
    )
    a = p.parse_args(argv)
    print(f"machine: {machine()}")
    if a.quick:
        print_rows(rows(2.0, 1, sizing=False))
    else:
        print_rows(rows(a.seconds, a.runs, sizing=not a.row, shares=a.shares))


if __name__ == "__main__":
    main()
