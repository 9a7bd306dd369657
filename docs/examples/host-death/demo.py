"""Host death on a wire (docs/simulator.md#host-death-rehearsed).

The drives of configs/shared-bus.yaml in ``abh3 simulate``, a supervisor moving them and
python-can's own logger listening — all on udp_multicast inside a network namespace with
only ``lo``, so nothing leaves the machine. The supervisor is killed with -9 (``--signal
STOP``: frozen) while the drives turn; they stop by their own command-zero timeout (0x4117 =
``drive_timeout_ms``, 300 ms). Needs the right to make a namespace (root, or ``unshare -r``).

    python docs/examples/host-death/demo.py [--signal KILL|STOP] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import can

from abh3_supervisor.runtime.netns import Namespace

ROOT = Path(__file__).resolve().parents[3]
CONFIG = ROOT / "configs" / "shared-bus.yaml"
DRIVES = {"left": 1, "right": 3}  # as the file says
ABH3 = [sys.executable, "-m", "abh3_supervisor"]


def clock(t: float) -> str:
    return datetime.fromtimestamp(t).strftime("%H:%M:%S.%f")[:-3]


def last_commands(wire: Path) -> dict[str, float]:
    """Per drive, the last DP0 command the listener heard (PF 0xEF, PS = the drive)."""
    last = dict.fromkeys(DRIVES, 0.0)
    for msg in can.LogReader(str(wire)):
        pf, ps = msg.arbitration_id >> 16 & 0xFF, msg.arbitration_id >> 8 & 0xFF
        for name, address in DRIVES.items():
            if pf == 0xEF and ps == address and len(msg.data) == 8:
                last[name] = max(last[name], msg.timestamp)
    return last


def summary(wire: Path, trace: Path) -> list[str]:
    events = [json.loads(line) for line in trace.read_text().splitlines()]
    lines = []
    for name, last in last_commands(wire).items():
        lines.append(f"{name}: last command on the wire   {clock(last)}")
        for e in events:
            if e["unit"] == name and e["event"] in ("command_zero_timeout", "standing"):
                at = e.get("at", e["t"])
                if at > last:
                    what = "its own timeout (0x4117)" if "at" in e else "standing"
                    lines.append(f"{name}: {what:<26} {clock(at)}  +{(at - last) * 1000:.0f} ms")
    return lines


def demo(how: signal.Signals, out: Path) -> list[str]:
    trace, wire = out / "trace.jsonl", out / "wire.log"
    with Namespace() as ns:
        sim = ns.popen(
            [*ABH3, "simulate", str(CONFIG), "--trace", str(trace)],
            stdout=subprocess.PIPE,
            stderr=(out / "simulate.err").open("w"),
        )
        assert sim.stdout is not None
        sim.stdout.readline()  # "ready: …": the drives listen
        listener = ns.popen(
            [
                sys.executable,
                "-m",
                "can.logger",
                "-i",
                "udp_multicast",
                "-c",
                "239.74.163.2",
                "-f",
                str(wire),
            ],
            stdout=subprocess.DEVNULL,
        )
        sup = ns.popen(
            [*ABH3, "run", str(CONFIG), "--headless", "--no-socket"],
            stderr=(out / "supervisor.err").open("w"),
        )
        time.sleep(3)  # the drives turn
        print(f"kill -{how.name[3:]} the supervisor (pid {sup.pid})")
        sup.send_signal(how)
        time.sleep(1.5)  # the drives stop by themselves
        for proc in (listener, sim):
            proc.send_signal(signal.SIGINT)
            proc.wait(10)
        sup.kill()
        sup.wait()
    return summary(wire, trace)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--signal", choices=["KILL", "STOP"], default="KILL")
    p.add_argument("--keep", type=Path, help="keep the trace, the wire and the logs here")
    a = p.parse_args()
    out = a.keep or Path(tempfile.mkdtemp(prefix="abh3-host-death-"))
    out.mkdir(parents=True, exist_ok=True)
    print("\n".join(demo(signal.Signals[f"SIG{a.signal}"], out)))
    print(f"files: {out}")


if __name__ == "__main__":
    main()
