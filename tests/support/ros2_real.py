"""The real ROS 2 side of the tests (tests/test_ros2_real.py, tests/test_ros2_robot_real.py):
the cached venv of a distro's wheels from the registry with this checkout and the built
interface, the probe and the network-namespace runner; skips (fails in CI) with the reason
when something is missing."""

from __future__ import annotations

import functools
import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients import ros2_interface as ri

ROOT = Path(__file__).resolve().parent.parent.parent
DECODE = [sys.executable, "-m", "abh3_supervisor", "decode"]
PROBE = ROOT / "tests" / "ros2_probe.py"
RUNNER = ROOT / "tests" / "ros2_netns_run.py"
NETNS = ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$@"', "sh"]


def unavailable(reason: str) -> None:
    """Skip outside CI; in CI the real-ROS proof must run, so it fails with the reason."""
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"real ROS 2 test cannot run in CI: {reason}", pytrace=False)
    pytest.skip(reason)


def _bridge_requirements() -> list[str]:
    """The supervisor's own runtime dependencies (for ``abh3 run`` in the ROS venv)."""
    reqs = importlib.metadata.requires("abh3-supervisor") or []
    return sorted(r for r in reqs if "extra ==" not in r)


PROBE_INSTALL = (
    "import os, abh3_supervisor, abh3_plugins.ros2; "
    "print(os.path.dirname(abh3_supervisor.__file__))"
)


@functools.cache
def ros_env(distro: str) -> tuple[Path, Path]:
    """The cached ROS venv (with this checkout installed) and the built interface prefix."""
    venv = ri.ensure_venv(distro, runtime=True, extra=_bridge_requirements())
    prefix = ri.cached_build(venv)
    python = str(venv / "bin" / "python")
    where = subprocess.run(
        [python, "-c", PROBE_INSTALL],
        capture_output=True,
        text=True,
        check=False,
        cwd="/",  # not this checkout's directory: what the venv itself imports
        env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"},
    ).stdout.strip()
    if where != str(ROOT / "abh3_supervisor"):  # this checkout, not another's
        with ri._locked(venv.parent / f"{venv.name}.project.lock"):
            ri._run(
                [python, "-m", "pip", "install", "-q", "--no-deps", "-e", str(ROOT)],
                "installing this checkout into the ROS venv",
            )
    return venv, prefix


def ros_distro(distro: str) -> tuple[str, Path, Path]:
    """The distro, its cached venv and interface prefix; or skip (fail in CI) with why."""
    for tool in ("cmake", "make", "c++", "unshare", "ip"):
        if shutil.which(tool) is None:
            unavailable(f"{tool} is not installed (apt-get install cmake make g++ iproute2)")
    ns = subprocess.run(
        ["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True, text=True
    )
    if ns.returncode != 0:
        unavailable(f"no network namespace (unshare -n): {ns.stderr.strip()}")
    try:
        venv, prefix = ros_env(distro)
    except (ri.BuildError, OSError, subprocess.CalledProcessError) as exc:
        unavailable(f"ROS 2 {distro} from the registry: {exc}")
    return distro, venv, prefix


def bridge_and_probe(
    bridge: list[str],
    bridge_env: dict[str, str],
    probe: list[str],
    probe_env: dict[str, str],
    log_dir: Path,
    record: Path,
    cfg: Path,
) -> tuple[dict[str, Any], str, list[dict[str, Any]]]:
    """Run the bridge and the probe together in a namespace with only loopback; the run's
    report (checked: the probe ran without errors, the bridge exited 0 without a
    traceback), the report as text for assertion messages, and the recorded frames."""
    job = {
        "bridge": bridge,
        "bridge_env": bridge_env,
        "bridge_log": str(log_dir / "bridge.err"),
        "probe": probe,
        "probe_env": probe_env,
        "timeout": 150,
    }
    done = subprocess.run(
        [*NETNS, sys.executable, str(RUNNER), json.dumps(job)],
        capture_output=True,
        text=True,
        timeout=240,
        cwd=ROOT,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    report = json.dumps(out, indent=1)[-8000:]
    assert out["probe"] is not None, report
    assert out["probe"]["errors"] == [], report
    assert out["bridge_rc"] == 0, report
    assert "Traceback" not in out["bridge_err"], report
    decoded = subprocess.run(
        [*DECODE, str(record), "--json", "--config", str(cfg)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    return out, report, [json.loads(line) for line in decoded]
