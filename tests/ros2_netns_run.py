"""Inside a network namespace with only ``lo``: start ``abh3 run``, run the rclpy probe, stop.

Started by tests/test_ros2_real.py as ``unshare -n sh -c 'ip link set lo up && exec …'``,
so every DDS process of the test lives here and nothing leaves the machine. Prints one
JSON object: the probe's report, the supervisor's exit code and the tail of its log.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys


def main() -> int:
    job = json.loads(sys.argv[1])
    with open(job["bridge_log"], "w") as log:
        bridge = subprocess.Popen(
            job["bridge"], env={**os.environ, **job["bridge_env"]}, stderr=log, text=True
        )
        out: dict[str, object] = {}
        try:
            probe = subprocess.run(
                job["probe"],
                env={**os.environ, **job["probe_env"]},
                capture_output=True,
                text=True,
                timeout=job["timeout"],
                check=False,
            )
            out["probe_rc"] = probe.returncode
            out["probe_err"] = probe.stderr[-3000:]
            try:
                out["probe"] = json.loads(probe.stdout.strip().splitlines()[-1])
            except (IndexError, ValueError):
                out["probe"] = None
                out["probe_out"] = probe.stdout[-3000:]
        except subprocess.TimeoutExpired:
            out["probe"] = None
            out["probe_err"] = f"the probe did not finish within {job['timeout']} s"
        finally:
            bridge.send_signal(signal.SIGINT)
            try:
                out["bridge_rc"] = bridge.wait(timeout=30)
            except subprocess.TimeoutExpired:
                bridge.kill()
                out["bridge_rc"] = "killed after 30 s"
    with open(job["bridge_log"]) as f:
        out["bridge_err"] = f.read()[-6000:]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
