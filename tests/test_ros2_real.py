"""The bridge against a REAL rclpy (ROS 2 Kilted and Jazzy wheels from the registry).

Per distro, a virtual environment of the ROS 2 wheels is made once and cached outside the
repository (``~/.cache/abh3-ros2/<distro>-<hash of the package list>``), and
``abh3_can_interface`` is built in it with cmake (``abh3 ros2 build-interface``'s code).
Each scenario runs ``abh3 run --headless`` on a simulated drive and a real rclpy node
(tests/ros2_probe.py, Fast DDS, the distro's default RMW) in one network namespace that
has only ``lo`` — nothing leaves the machine — and checks the graph, the endpoint names,
the documented topics and types, /diagnostics, odom, cmd_vel reaching the DP0 frames
(from the supervisor's recording) and the zero after command_timeout_ms, the service, and
``allow_commands: false``. Both of our transports: ``dds`` (cyclonedds) and ``rclpy``.

Without the wheels (no registry), cmake, a C++ compiler or network namespaces the tests
skip with the reason — and FAIL in CI (``CI=true``), where they must run.
"""

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
from abh3_supervisor.core.kinematics import Geometry, twist_to_yx

ROOT = Path(__file__).resolve().parent.parent
DECODE = [sys.executable, "-m", "abh3_supervisor", "decode"]
PROBE = ROOT / "tests" / "ros2_probe.py"
RUNNER = ROOT / "tests" / "ros2_netns_run.py"
NETNS = ["unshare", "-n", "sh", "-c", 'ip link set lo up && exec "$@"', "sh"]
TIMEOUT_MS = 300
PERIOD = 1 / 50  # the default DP0 exchange rate
TWIST = (0.2, 0.5)
CONFIG = """
buses:
  demo: {{interface: virtual, channel: real-{name}, simulate: true}}
units:
  - name: left
    abh3_id: 1
    broadcast: {{mask: 0x13, rate_hz: 20}}
    geometry: {{pulses_per_rev: 4096}}
    startup: ["SERVO ON ON", "START ON ON"]
plugins:
  ros2: {{domain_id: {domain}, transport: {transport}, allow_commands: {allow},
          command_timeout_ms: {timeout}}}
"""
TOPICS = {  # docs/ros2.md's names and types, those this unit has
    "/left/odom": ["nav_msgs/msg/Odometry"],
    "/diagnostics": ["diagnostic_msgs/msg/DiagnosticArray"],
    "/left/vel_fbk_ab": ["abh3_can_interface/msg/Abh3Velocity"],
    "/left/vel_fbk_yx": ["abh3_can_interface/msg/Abh3Velocity"],
    "/left/brd0_data": ["abh3_can_interface/msg/Abh3Brd0"],
    "/left/brd1_data": ["abh3_can_interface/msg/Abh3Brd1"],
    "/left/brd4_data": ["abh3_can_interface/msg/Abh3Brd4"],
    "/left/xa_yx": ["abh3_can_interface/msg/Abh3Velocity"],
    "/left/brd_num": ["std_msgs/msg/Int32"],
}
COMMAND_TOPICS = {
    "/left/cmd_vel": ["geometry_msgs/msg/Twist"],
    "/left/vel_cmd": ["abh3_can_interface/msg/Abh3Velocity"],
}


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


@pytest.fixture(scope="module", params=["kilted", "jazzy"])
def ros(request: pytest.FixtureRequest) -> tuple[str, Path, Path]:
    for tool in ("cmake", "make", "c++", "unshare", "ip"):
        if shutil.which(tool) is None:
            unavailable(f"{tool} is not installed (apt-get install cmake make g++ iproute2)")
    ns = subprocess.run(
        ["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True, text=True
    )
    if ns.returncode != 0:
        unavailable(f"no network namespace (unshare -n): {ns.stderr.strip()}")
    try:
        venv, prefix = ros_env(request.param)
    except (ri.BuildError, OSError, subprocess.CalledProcessError) as exc:
        unavailable(f"ROS 2 {request.param} from the registry: {exc}")
    return request.param, venv, prefix


def scenario(
    ros: tuple[str, Path, Path], tmp_path: Path, transport: str, allow: bool, domain: int
) -> dict[str, Any]:
    distro, venv, prefix = ros
    cfg = tmp_path / "ros2.yaml"
    cfg.write_text(
        CONFIG.format(
            name=f"{distro}-{transport}",
            domain=domain,
            transport=transport,
            allow=str(allow).lower(),
            timeout=TIMEOUT_MS,
        )
    )
    site, lib = str(ri.site_dir(prefix)), str(prefix / "lib")
    ros_side = {
        "PYTHONPATH": site,
        "LD_LIBRARY_PATH": lib,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",  # no discovery multicast
        "ROS_DOMAIN_ID": str(domain),
    }
    from abh3_plugins.ros2.dds import LOOPBACK_URI

    record = tmp_path / "run.log"
    run = ["-m", "abh3_supervisor", "run", str(cfg), "--headless", "--duration", "120"]
    run += ["--record", str(record), "--no-socket"]
    if transport == "dds":
        bridge, bridge_env = [sys.executable, *run], {"CYCLONEDDS_URI": LOOPBACK_URI}
    else:
        bridge, bridge_env = [str(venv / "bin" / "python"), *run], ros_side
    args = {
        "domain": domain,
        "topics": sorted({**TOPICS, **(COMMAND_TOPICS if allow else {})}),
        "published": ["/left/odom", "/diagnostics"],
        "subscribed": ["/left/cmd_vel"] if allow else [],
        "odom": "/left/odom",
        "cmd_vel": "/left/cmd_vel",
        "twist": list(TWIST),
        "wait": 30,
        "drive": 2.0,
    }
    if transport == "rclpy" or not allow:
        args["service"] = "/left/inp_service"
        args["commands"] = ["SERVO ON ON", "FOO"] if allow else []
        if not allow:
            args["wait"] = 30
    job = {
        "bridge": bridge,
        "bridge_env": bridge_env,
        "bridge_log": str(tmp_path / "bridge.err"),
        "probe": [str(venv / "bin" / "python"), str(PROBE), json.dumps(args)],
        "probe_env": ros_side,
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
    out["dp0"] = [
        (f["t"], f["values"]["cmd_ay"], f["values"]["cmd_bx"])
        for f in map(json.loads, decoded)
        if f["kind"] == "dp0_command"
    ]
    out["report"] = report
    return out


def check_common(out: dict[str, Any], transport: str) -> dict[str, Any]:
    p, report = out["probe"], out["report"]
    assert p["in_graph"], report
    assert "/abh3_supervisor" in p["nodes"], report
    for topic, types in TOPICS.items():
        assert p["topics"].get(topic) == types, (topic, report)
    assert {"/left/odom", "/diagnostics", "/left/vel_fbk_ab"} <= set(p["node_publishers"])
    assert ["abh3_supervisor: bus demo", "can demo"] in p["diagnostics"], report
    assert ["abh3_supervisor: unit left", "abh3 demo/1"] in p["diagnostics"], report
    assert p["odom"]["frame_id"] == "odom" and p["odom"]["child_frame_id"] == "base_link"
    return p  # type: ignore[no-any-return]


def check_drive(out: dict[str, Any]) -> None:
    p, report = out["probe"], out["report"]
    assert p["cmd_vel_matched"] >= 1, report
    y, x = twist_to_yx(*TWIST, Geometry())
    first, last = p["cmd_vel"]["first"], p["cmd_vel"]["last"]
    during = [(t, ay, bx) for t, ay, bx in out["dp0"] if first <= t <= last + 0.05]
    moving = [d for d in during if abs(d[1] - y) < 0.2 and abs(d[2] - x) < 0.2]
    assert moving, f"no DP0 frame carried Y {y:.1f} X {x:.1f}: {during[-5:]}\n{report}"
    after = [(t, ay, bx) for t, ay, bx in out["dp0"] if t > last]
    zero = next((t for t, ay, bx in after if ay == 0 and bx == 0), None)
    assert zero is not None, f"never zeroed after cmd_vel stopped: {after[:5]}"
    # silence longer than command_timeout_ms zeroes the unit: the next period's frame is 0
    late = zero - last
    assert late <= TIMEOUT_MS / 1000 + PERIOD + 0.03, f"zero {late * 1000:.0f} ms after the last"


def endpoints_named(out: dict[str, Any], known_gap: bool) -> None:
    """Per-topic endpoint info names our node (``ros2 topic info -v``)."""
    named = {t: n for t, n in out["probe"]["endpoints"].items() if n != ["/abh3_supervisor"]}
    if named and known_gap:  # everything else held; this one is open (docs/ros2.md)
        pytest.xfail(f"endpoints not mapped to /abh3_supervisor by rmw_fastrtps: {named}")
    assert not named, out["report"]


def test_dds_transport_against_real_rclpy(ros: tuple[str, Path, Path], tmp_path: Path) -> None:
    out = scenario(ros, tmp_path, "dds", True, 31)
    check_common(out, "dds")
    check_drive(out)
    endpoints_named(out, known_gap=True)


def test_rclpy_transport_with_the_built_interface(
    ros: tuple[str, Path, Path], tmp_path: Path
) -> None:
    out = scenario(ros, tmp_path, "rclpy", True, 32)
    p = check_common(out, "rclpy")
    assert "over RclpyTransport" in out["bridge_err"], out["report"]
    assert p["service_ready"], out["report"]
    assert p["answers"] == ["", "Invalid Command."], out["report"]
    check_drive(out)
    endpoints_named(out, known_gap=False)


def test_allow_commands_false_refuses(ros: tuple[str, Path, Path], tmp_path: Path) -> None:
    out = scenario(ros, tmp_path, "dds", False, 33)
    p = check_common(out, "dds")
    assert not p["service_ready"], out["report"]  # the service is not even created
    assert p["cmd_vel_matched"] == 0, out["report"]
    assert all(ay == 0 and bx == 0 for _, ay, bx in out["dp0"]), "a command moved the drive"


def test_forced_rclpy_without_the_interface_is_an_error(
    ros: tuple[str, Path, Path], tmp_path: Path
) -> None:
    """check and run judge alike: FILE:LINE, exit 2, before any drive starts."""
    _, venv, _ = ros
    cfg = tmp_path / "ros2.yaml"
    cfg.write_text(
        CONFIG.format(name="noif", domain=34, transport="rclpy", allow="false", timeout=500)
    )
    line = next(n for n, t in enumerate(cfg.read_text().splitlines(), 1) if "transport:" in t)
    for command in (["check", str(cfg)], ["run", str(cfg), "--headless", "--duration", "5"]):
        done = subprocess.run(
            [str(venv / "bin" / "python"), "-m", "abh3_supervisor", *command],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=ROOT,
            check=False,
            env={k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "LD_LIBRARY_PATH")},
        )
        assert done.returncode == 2, (command, done.stderr)
        assert f"{cfg}:{line}: plugins.ros2.transport: rclpy is importable but" in done.stderr
        assert "abh3_can_interface" in done.stderr
