"""The bridge against a REAL rclpy (ROS 2 Kilted and Jazzy wheels from the registry).

Per distro, a virtual environment of the ROS 2 wheels is made once and cached outside the
repository (``~/.cache/abh3-ros2/<distro>-<hash of the package list>``), and
``abh3_can_interface`` is built in it with cmake (``abh3 ros2 build-interface``'s code).
Each scenario runs ``abh3 run --headless`` on a simulated drive and a real rclpy node
(tests/ros2_probe.py, Fast DDS, the distro's default RMW) in one network namespace that
has only ``lo`` — nothing leaves the machine. Per distro and per transport (``dds``,
cyclonedds, and ``rclpy``) one run checks the graph (node, its endpoints by node, the
node named per topic), the documented topics and types, /diagnostics per bus and unit,
odom's frame ids and twist, cmd_vel reaching the DP0 frames (from the supervisor's
recording) and the zero after command_timeout_ms, the service (called over rclpy: the
answers and the frames that carried the change); a second run ``allow_commands: false``.

Without the wheels (no registry), cmake, a C++ compiler or network namespaces the tests
skip with the reason — and FAIL in CI (``CI=true``), where they must run.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients import ros2_interface as ri
from abh3_supervisor.core.kinematics import Geometry, twist_to_yx
from tests.support.ros2_real import PROBE, ROOT, bridge_and_probe, ros_distro

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

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
SERVICE = "/left/inp_service"
COMMANDS = ["START OFF OFF", "START ON ON", "FOO"]  # stop, start again, a wrong command
# rmw_fastrtps 9.3 (Kilted) takes an endpoint's participant from PID_PARTICIPANT_GUID,
# which Cyclone DDS never sends (Fast DDS 3.2.3 derives the key, not participant_guid, from
# the GUID prefix): every Cyclone endpoint, rmw_cyclonedds's too, is named so (docs/ros2.md)
BARE = "_CREATED_BY_BARE_DDS_APP_/_CREATED_BY_BARE_DDS_APP_"


@pytest.fixture(scope="module", params=["kilted", "jazzy"])
def ros(request: pytest.FixtureRequest) -> tuple[str, Path, Path]:
    return ros_distro(request.param)


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
        "service": SERVICE,
        # a Fast DDS client takes no reply from Cyclone (docs/ros2.md): calls need rclpy
        "commands": COMMANDS if allow and transport == "rclpy" else [],
        "expect_commands": allow,
        "twist": list(TWIST),
        "wait": 30,
        "absent_wait": 3,
        "drive": 2.0,
    }
    probe = [str(venv / "bin" / "python"), str(PROBE), json.dumps(args)]
    out, report, frames = bridge_and_probe(
        bridge, bridge_env, probe, ros_side, tmp_path, record, cfg
    )
    commands = [f for f in frames if f["kind"] == "dp0_command"]
    out["dp0"] = [(f["t"], f["values"]["cmd_ay"], f["values"]["cmd_bx"]) for f in commands]
    out["dp0_inputs"] = [(f["t"], set(f["flags"]["inputs"])) for f in commands]
    out["report"] = report
    return out


def check_common(out: dict[str, Any], allow: bool) -> dict[str, Any]:
    """The graph, the documented topics and types, /diagnostics, odom at rest."""
    p, report = out["probe"], out["report"]
    assert p["in_graph"], report
    assert "/abh3_supervisor" in p["nodes"], report
    for topic, types in TOPICS.items():
        assert p["topics"].get(topic) == types, (topic, report)
    # the node's endpoints, found through the GIDs our ros_discovery_info lists: these
    # equal the GIDs rmw made of the DDS endpoints it discovered
    assert {"/left/odom", "/diagnostics", "/left/vel_fbk_ab"} <= set(p["node_publishers"])
    assert ("/left/cmd_vel" in p["node_subscribers"]) is allow, report
    assert ["abh3_supervisor: bus demo", "can demo"] in p["diagnostics"], report
    assert ["abh3_supervisor: unit left", "abh3 demo/1"] in p["diagnostics"], report
    odom = p["odom"]
    assert (odom["frame_id"], odom["child_frame_id"]) == ("odom", "base_link"), report
    assert (odom["linear_x"], odom["angular_z"]) == (0.0, 0.0), report  # standing still
    return p  # type: ignore[no-any-return]


def endpoints_named(out: dict[str, Any], distro: str, transport: str) -> None:
    """Per-topic endpoint info (``ros2 topic info -v``) names our node."""
    p = out["probe"]
    named = {t: n for t, n in p["endpoints"].items() if n != ["/abh3_supervisor"]}
    assert all(len(g) == 1 for g in p["endpoint_gids"].values()), out["report"]  # ours alone
    if distro == "kilted" and transport == "dds" and named:
        # the upstream gap above and nothing else: wrong GIDs of ours would show as
        # _NODE_NAME_UNKNOWN_ (participant found, endpoint not) and fail here
        assert all(n == [BARE] for n in named.values()), out["report"]
        pytest.xfail(f"rmw_fastrtps 9.3 with Cyclone DDS endpoints (docs/ros2.md): {named}")
    assert not named, out["report"]


def check_drive(out: dict[str, Any]) -> None:
    """cmd_vel reaches the DP0 frames, odom shows the twist, silence zeroes in time."""
    p, report = out["probe"], out["report"]
    assert p["cmd_vel_matched"] >= 1, report
    y, x = twist_to_yx(*TWIST, Geometry())
    first, last = p["cmd_vel"]["first"], p["cmd_vel"]["last"]
    during = [(t, ay, bx) for t, ay, bx in out["dp0"] if first <= t <= last + 0.05]
    moving = [d for d in during if abs(d[1] - y) < 0.2 and abs(d[2] - x) < 0.2]
    assert moving, f"no DP0 frame carried Y {y:.1f} X {x:.1f}: {during[-5:]}\n{report}"
    # the drive followed (3000 min⁻¹/s ramp: well within the 2 s): odom's twist is cmd_vel's
    driving = p["odom_driving"]
    assert abs(driving["linear_x"] - TWIST[0]) < 0.005, report
    assert abs(driving["angular_z"] - TWIST[1]) < 0.01, report
    after = [(t, ay, bx) for t, ay, bx in out["dp0"] if t > last]
    zero = next((t for t, ay, bx in after if ay == 0 and bx == 0), None)
    assert zero is not None, f"never zeroed after cmd_vel stopped: {after[:5]}"
    # silence longer than command_timeout_ms zeroes the unit: the next period's frame is 0
    late = zero - last
    assert late <= TIMEOUT_MS / 1000 + PERIOD + 0.03, f"zero {late * 1000:.0f} ms after the last"


def check_service(out: dict[str, Any]) -> None:
    """inp_service answers as the seed does, after the drive got the change."""
    p, report = out["probe"], out["report"]
    assert p["service_ready"], report
    assert p["answers"] == ["", "", "Invalid Command."], report
    start = {"AY_START", "BX_START"}  # the input bits' names, as `abh3 decode` gives them
    (off_sent, off_done), (on_sent, on_done), _ = p["calls"]

    def inputs(t0: float, t1: float) -> list[set[str]]:
        return [i for t, i in out["dp0_inputs"] if t0 <= t <= t1]

    assert start <= inputs(0, off_sent)[-1], report  # running (startup) before
    assert any(not start & i for i in inputs(off_sent, off_done)), "START OFF OFF not sent"
    assert any(start <= i for i in inputs(on_sent, on_done)), "START ON ON not sent"


@pytest.mark.parametrize("transport", ["dds", "rclpy"])
def test_bridge_against_real_rclpy(
    ros: tuple[str, Path, Path], tmp_path: Path, transport: str
) -> None:
    """Everything of the issue's check but the refusal: one run per distro and transport."""
    distro = ros[0]
    out = scenario(ros, tmp_path, transport, True, 31 if transport == "dds" else 32)
    p = check_common(out, allow=True)
    assert p["services"] == {SERVICE: ["abh3_can_interface/srv/Abh3Input"]}, out["report"]
    if transport == "rclpy":
        assert "over RclpyTransport" in out["bridge_err"], out["report"]
        check_service(out)
    check_drive(out)
    endpoints_named(out, distro, transport)


@pytest.mark.parametrize("transport", ["dds", "rclpy"])
def test_allow_commands_false_refuses(
    ros: tuple[str, Path, Path], tmp_path: Path, transport: str
) -> None:
    out = scenario(ros, tmp_path, transport, False, 33 if transport == "dds" else 35)
    p = check_common(out, allow=False)
    assert p["services"] == {}, out["report"]  # the service is not even created
    assert p["cmd_vel_matched"] == 0, out["report"]
    assert out["dp0"], "no DP0 frame recorded"
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
