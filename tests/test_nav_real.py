"""A Nav2 base against a REAL rclpy (issue 51, item 7): the ROS 2 Kilted and Jazzy wheels of
tests/test_ros2_real.py's cached environments (with sensor_msgs, and tf2_msgs built from
its upstream definition), ``abh3 run`` on a simulated two-drive AGV (docs/nav2.md's
example) and a probe (tests/ros2_probe.py, ``mode: nav``) in one network namespace that
has only ``lo``, discovery kept to the host.

The probe subscribes ``/agv/odom``, ``/tf``, ``/agv/joint_states`` and ``/diagnostics``
from the start, and acts as joint_state_topic_hardware_interface: JointState commands on
``/agv/joint_commands`` at the controller rate (50 Hz), in phases — at rest, driving, the
robot switched off through ``/agv/enable`` while the commands go on (refused by the robot
decision), switched on again, then silence. Everything is held against the supervisor's
recording of the same run: the DP0 replies (the simulated drives' own velocity feedback,
what the robot truly did) and the DP0 commands (what reached the wire).

No absolute time bound: rates are counted against the DP0 replies counted on the wire
over the same window, and the lapse to zero in command periods of the scheduler's own.
"""

from __future__ import annotations

import itertools
import json
import math
import statistics
import sys
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.config.advice import warnings
from abh3_supervisor.core.robot import RobotConfig, motor_speeds, twist_of
from tests.support.ros2_real import PROBE, bridge_and_probe, ros_distro

TWIST = (0.2, 0.5)  # what the controller asks of the base [m/s, rad/s]
TIMEOUT_MS = 300
RATE_HZ = 50.0  # the command rate: the drives' DP0 exchanges, the controller's cycle
JOINTS = ("left_wheel_joint", "right_wheel_joint")
CONFIG = """
buses:
  demo: {{interface: virtual, channel: nav-{name}, simulate: true}}
units:
  - {{name: left_drive, abh3_id: 1, velocity_model: motor, broadcast: {{mask: 0x13, rate_hz: 60}},
     startup: ["SERVO ON ON", "START ON ON"]}}
  - {{name: right_drive, abh3_id: 3, velocity_model: motor, broadcast: {{mask: 0x13, rate_hz: 60}},
     startup: ["SERVO ON ON", "START ON ON"]}}
robots:
  - name: agv
    track_m: 0.45
    diameter_m: 0.2
    gear_ratio: 20
    pulses_per_rev: 4096
    limits: {{linear_mps: 0.8, angular_radps: 1.5, linear_accel_mps2: 0.5,
              angular_accel_radps2: 1.5}}
    frame_id: odom
    child_frame_id: base_link
    wheels:
      - {{unit: left_drive, axis: A, side: left}}
      - {{unit: right_drive, axis: A, side: right, sign: -1}}
plugins:
  ros2:
    domain_id: {domain}
    transport: {transport}
    distro: {distro}
    allow_commands: true
    command_timeout_ms: {timeout}
    diagnostics_hz: 0        # /diagnostics only when a level changes: each one is a change
    robots:
      agv: {{joints: {{left_drive.A: left_wheel_joint, right_drive.A: right_wheel_joint}}}}
"""
# (name, whether JointState commands go out, the enable command at its start, seconds)
PHASES_ENABLE: list[tuple[str, bool, str | None, float]] = [
    ("rest", False, None, 1.0),
    ("drive", True, None, 3.0),
    ("off", True, "OFF", 1.5),
    ("on", True, "ON", 2.5),
    ("silence", False, None, 1.5),
]
PHASES = [p for p in PHASES_ENABLE if p[0] not in ("off", "on")]  # Fast DDS client: no calls


def joint_velocities(robot: RobotConfig, linear_x: float, angular_z: float) -> list[float]:
    """Each wheel joint's speed [rad/s] for a twist: positive rolling the robot forward."""
    out = []
    for w in robot.wheels:
        side = -1.0 if w.side.value == "left" else 1.0
        out.append((linear_x + side * angular_z * robot.track_m / 2) / (w.diameter_m / 2))
    return out


@pytest.fixture(scope="module", params=["kilted", "jazzy"])
def ros(request: pytest.FixtureRequest) -> tuple[str, Path, Path]:
    return ros_distro(request.param)


def run(ros: tuple[str, Path, Path], tmp_path: Path, transport: str) -> dict[str, Any]:
    """One bridge run and one probe in a namespace; the probe's report and the frames."""
    from abh3_plugins.ros2.dds import LOOPBACK_URI
    from abh3_supervisor.clients import ros2_interface as ri

    distro, venv, prefix = ros
    domain = {"kilted": 50, "jazzy": 52}[distro] + (1 if transport == "dds" else 0)
    cfg = tmp_path / "agv.yaml"
    cfg.write_text(
        CONFIG.format(
            name=f"{distro}-{transport}",
            domain=domain,
            transport=transport,
            distro=distro,
            timeout=TIMEOUT_MS,
        )
    )
    robot = parse_config(cfg.read_text(), str(cfg)).robots["agv"]
    ros_side = {
        "PYTHONPATH": str(ri.site_dir(prefix)),
        "LD_LIBRARY_PATH": str(prefix / "lib"),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",  # no discovery multicast
        "ROS_DOMAIN_ID": str(domain),
    }
    record = tmp_path / "run.log"
    command = ["-m", "abh3_supervisor", "run", str(cfg), "--headless", "--duration", "120"]
    command += ["--record", str(record), "--no-socket"]
    if transport == "dds":
        bridge, bridge_env = [sys.executable, *command], {"CYCLONEDDS_URI": LOOPBACK_URI}
    else:
        bridge, bridge_env = [str(venv / "bin" / "python"), *command], ros_side
    drive = joint_velocities(robot, *TWIST)
    phases = PHASES_ENABLE if transport == "rclpy" else PHASES
    args = {
        "mode": "nav",
        "domain": domain,
        "odom": "/agv/odom",
        "tf": "/tf",
        "joint_states": "/agv/joint_states",
        "joint_commands": "/agv/joint_commands",
        "robot_status": "abh3_supervisor: robot agv",
        # a Fast DDS client takes no reply from Cyclone (docs/ros2.md): calls need rclpy
        "enable": "/agv/enable" if transport == "rclpy" else None,
        "joints": list(JOINTS),
        "rate_hz": RATE_HZ,
        "phases": [[n, drive if d else None, e, s] for n, d, e, s in phases],
        "wait": 30,
    }
    probe = [str(venv / "bin" / "python"), str(PROBE), json.dumps(args)]
    out, report, frames = bridge_and_probe(
        bridge, bridge_env, probe, ros_side, tmp_path, record, cfg
    )
    out["frames"], out["report"], out["robot"] = frames, report, robot
    out["phases"] = {p["name"]: p for p in out["probe"]["phases"]}
    return out


def wheel_speeds(frames: list[dict[str, Any]], robot: RobotConfig) -> list[tuple[float, Any]]:
    """Every DP0 reply of the robot's drives: (time, every axis's motor speed so far), once
    each drive has replied (the simulated drives' own velocity feedback)."""
    speeds: dict[tuple[str, int], float] = {}
    out = []
    for f in frames:
        if f["kind"] != "dp0_reply" or f.get("unit") not in robot.units:
            continue
        speeds[f["unit"], 0] = f["values"]["vel_a"]
        speeds[f["unit"], 1] = f["values"]["vel_b"]
        if len(speeds) == 2 * len(robot.units):
            out.append((f["t"], dict(speeds)))
    return out


class Truth:
    """Where the robot truly was: its drives' velocity feedback (DP0 replies) integrated,
    the twist taken as changing linearly from one reply to the next (the drives ramp: a
    reply's speed held until the next would lag the robot by half a period)."""

    def __init__(self, robot: RobotConfig, frames: list[dict[str, Any]]) -> None:
        self.points: list[tuple[float, float, float, float, float, float]] = []
        x = y = yaw = 0.0
        for t, speeds in wheel_speeds(frames, robot):
            v, w = twist_of(robot, speeds)
            if self.points:
                t0, _, _, _, v0, w0 = self.points[-1]
                x, y, yaw = self._step(x, y, yaw, (v0 + v) / 2, (w0 + w) / 2, t - t0)
            self.points.append((t, x, y, yaw, v, w))

    @staticmethod
    def _step(
        x: float, y: float, yaw: float, v: float, w: float, dt: float
    ) -> tuple[float, float, float]:
        return (
            x + v * math.cos(yaw + w * dt / 2) * dt,
            y + v * math.sin(yaw + w * dt / 2) * dt,
            yaw + w * dt,
        )

    def at(self, t: float) -> tuple[float, float, float, float, float]:
        """(x, y, yaw, v, w) at ``t``: the last reply's pose carried on by its twist."""
        import bisect

        i = bisect.bisect_right([p[0] for p in self.points], t) - 1
        t0, x, y, yaw, v, w = self.points[max(i, 0)]
        return (*self._step(x, y, yaw, v, w, max(0.0, t - t0)), v, w)


def within_window(stamps: list[float], t0: float, t1: float) -> int:
    return sum(1 for s in stamps if t0 <= s < t1)


def wheel_angles(frames: list[dict[str, Any]], robot: RobotConfig) -> list[list[Any]]:
    """Each wheel's angle [rad, forward positive] from the pulse counts on the wire
    (broadcast 4): per wheel, (time, angle) at each of its unit's reports."""
    out = []
    for w in robot.wheels:
        rad = w.sign * 2 * math.pi / (w.pulses_per_rev * w.gear_ratio)
        key = f"pulse_{'ab'[w.axis]}"
        out.append(
            [
                (f["t"], f["values"][key] * rad)
                for f in frames
                if f["kind"] == "broadcast" and f.get("unit") == w.unit and key in f["values"]
            ]
        )
    return out


def at(series: list[tuple[float, float]], t: float) -> float:
    """A wheel's angle at ``t``, linear between two reports."""
    import bisect

    i = bisect.bisect_right([s[0] for s in series], t) - 1
    if i < 0 or i >= len(series) - 1:
        return series[max(i, 0)][1]
    (t0, a0), (t1, a1) = series[i], series[i + 1]
    return a0 + (a1 - a0) * (t - t0) / (t1 - t0)


def dp0(out: dict[str, Any], unit: str, t0: float, t1: float) -> list[tuple[float, float, float]]:
    """A unit's DP0 commands (time, A, B) sent in [t0, t1]."""
    return [
        (f["t"], f["values"]["cmd_ay"], f["values"]["cmd_bx"])
        for f in out["frames"]
        if f["kind"] == "dp0_command" and f["unit"] == unit and t0 <= f["t"] <= t1
    ]


def check_odometry(out: dict[str, Any]) -> dict[str, float]:
    """odom's rate against the DP0 replies on the wire, its frames, its twist and pose
    against the simulated drives' feedback and pulse counts; /tf and joint_states the
    same instants, poses and motion. Returns the figures measured."""
    p, report, robot = out["probe"], out["report"], out["robot"]
    phases, frames = out["phases"], out["frames"]
    odom, tfs, joints = p["odom"], p["tf"], p["joint_states"]
    figures: dict[str, float] = {}
    assert odom and tfs and joints, report

    # rate: one odom per round of DP0 replies (each drive's once), counted over the same
    # window on the wire (the middle of the run: driving, stopping, driving, stopping)
    t0, t1 = phases["drive"]["first"] + 0.5, phases["silence"]["start"] + 1.0
    stamps = [m[0] / 1e9 for m in odom]
    replies = {
        u: within_window([f["t"] for f in frames if f["kind"] == "dp0_reply" and f["unit"] == u],
                         t0, t1)
        for u in robot.units
    }  # fmt: skip
    published = within_window(stamps, t0, t1)
    figures["odom_per_round"] = published / min(replies.values())
    assert abs(published - min(replies.values())) <= 2, (published, replies, report)
    assert all(b > a for a, b in itertools.pairwise(stamps)), "stamps not increasing"

    # frames, and /tf: the same pose at the same stamp, one transform a message
    assert {(m[1], m[2]) for m in odom} == {("odom", "base_link")}, report
    assert {(t[1], t[2], t[7]) for t in tfs} == {("odom", "base_link", 1)}, report
    by_stamp = {m[0]: m for m in odom}
    common = [t for t in tfs if t[0] in by_stamp]
    # every odom the probe held has its transform (the first or last may be cut by the run)
    assert len(common) >= len(odom) - 2 and len(common) >= len(tfs) - 2, report
    for t in common:
        m = by_stamp[t[0]]
        assert (t[3], t[4], t[5], t[6]) == (m[3], m[4], 0.0, m[6]), (t, m)

    # twist: the latest DP0 replies of every drive before the stamp, to the bit
    truth = Truth(robot, frames)
    figures["twist_error"] = max(
        max(abs(m[7] - truth.at(m[0] / 1e9)[3]), abs(m[8] - truth.at(m[0] / 1e9)[4])) for m in odom
    )
    assert figures["twist_error"] < 1e-9, report
    driving = [
        m for m in odom if phases["drive"]["first"] + 1 < m[0] / 1e9 < phases["drive"]["last"]
    ]
    assert driving, report
    for m in driving:  # the asked twist, reached after the robot's ramp
        assert (m[7], m[8]) == pytest.approx(TWIST, abs=0.01), m

    # pose: the pulse counts' (broadcast 4 on the wire): yaw is the difference of the two
    # sides' travel whatever the path; between rounds odom carries it on with the feedback,
    # within the turn of one interval between counts of the counts interpolated (the
    # interval as measured on the wire)
    left, right = wheel_angles(frames, robot)
    r, track = robot.wheels[0].diameter_m / 2, robot.track_m
    wz = max(abs(m[8]) for m in odom)
    counts_every = statistics.median(b[0] - a[0] for a, b in itertools.pairwise(left))
    yaw_error = [m[5] - r * (at(right, m[0] / 1e9) - at(left, m[0] / 1e9)) / track for m in odom]
    figures["yaw_vs_counts_moving"] = max(map(abs, yaw_error))
    figures["yaw_vs_counts_final"] = abs(yaw_error[-1])
    assert figures["yaw_vs_counts_moving"] <= wz * counts_every, (figures, report)
    assert figures["yaw_vs_counts_final"] < 1e-9, (figures, report)  # at rest: exactly
    # against the drives' velocity feedback integrated (the sim's motion told by its
    # other output): the pose within the disagreement of its two outputs, counts and
    # feedback, measured in the same run (the control), and a millimetre / milliradian
    final = odom[-1]
    x, y, yaw, _, _ = truth.at(final[0] / 1e9)
    sim_yaw = abs(r * (right[-1][1] - left[-1][1]) / track - truth.at(right[-1][0])[2])
    figures["final_yaw_vs_feedback"] = abs(final[5] - yaw)
    figures["final_xy_vs_feedback"] = math.hypot(final[3] - x, final[4] - y)
    figures["sim_counts_vs_feedback_yaw"] = sim_yaw
    figures["turned"] = final[5]
    assert figures["final_yaw_vs_feedback"] <= sim_yaw + 0.001, (figures, report)
    assert figures["final_xy_vs_feedback"] <= 0.01, (figures, report)
    assert (final[7], final[8]) == (0.0, 0.0), report  # stopped

    # joint_states: with every odom, the robot's joints, velocities making odom's twist,
    # positions the counts' angles (to the bit at rest) and their yaw odom's
    assert all(j[1] == list(JOINTS) for j in joints), report
    assert len([j for j in joints if j[0] in by_stamp]) >= len(joints) - 2, report
    moving = 0.0
    for j in joints:
        m = by_stamp.get(j[0])
        if m is None:
            continue
        (pl, pr), (vl, vr) = j[2], j[3]
        assert r * (vl + vr) / 2 == pytest.approx(m[7], abs=1e-9), (j, m)
        assert r * (vr - vl) / track == pytest.approx(m[8], abs=1e-9), (j, m)
        moving = max(moving, abs(r * (pr - pl) / track - m[5]))
    figures["joint_yaw_vs_odom_moving"] = moving
    assert moving <= wz * counts_every, (figures, report)
    last = joints[-1]
    assert last[2] == pytest.approx([left[-1][1], right[-1][1]], abs=1e-9), report
    assert r * (last[2][1] - last[2][0]) / track == pytest.approx(by_stamp[last[0]][5], abs=1e-9)
    assert last[3] == [0.0, 0.0], report
    return figures


def check_commands(out: dict[str, Any]) -> dict[str, float]:
    """The JointState commands reached the wire as every wheel's motor speed (mounting
    sign included), and lapsed to zero once they stopped: within command_timeout_ms in
    the scheduler's own periods (counted frames, not wall time)."""
    report, robot, phases = out["report"], out["robot"], out["phases"]
    drive = phases["drive"]
    speeds = motor_speeds(robot, *TWIST)
    figures: dict[str, float] = {}
    for unit in robot.units:
        a, b = speeds[unit]
        sent = dp0(out, unit, drive["first"], drive["last"])
        carried = [f for f in sent if abs(f[1] - a) < 0.2 and abs(f[2] - b) < 0.2]
        # after the robot's acceleration ramp (0.5 m/s², 1.5 rad/s²: within half a second)
        assert len(carried) > len(sent) / 2, (unit, a, b, sent[-3:], report)
    assert speeds["right_drive"][0] < 0  # the mirrored wheel turns its motor backwards
    last = phases["on" if "on" in phases else "drive"]["last"]
    for unit in robot.units:
        after = dp0(out, unit, last, math.inf)
        zero = next((i for i, f in enumerate(after) if f[1] == 0 and f[2] == 0), None)
        assert zero is not None, f"{unit} never zeroed after the commands stopped: {after[:5]}"
        assert all(f[1] == 0 and f[2] == 0 for f in after[zero:]), (unit, after[zero:][:5])
        # the frames still moving after the last command: the timeout's periods, and one
        # for the way (the message's delivery, the period under way)
        periods = TIMEOUT_MS / 1000 * RATE_HZ
        figures[f"lapse_frames_{unit}"] = zero
        assert periods - 2 <= zero <= periods + 2, (unit, zero, periods, report)
    return figures


def check_refusal(out: dict[str, Any]) -> None:
    """/agv/enable OFF while the commands go on: answered, the robot's /diagnostics status
    says why it may not move at once (a level change), every DP0 command is zero and the
    bridge says the commands are refused; ON: ready again, and the commands move it."""
    p, report, phases, robot = out["probe"], out["report"], out["phases"], out["robot"]
    off, on = phases["off"], phases["on"]
    assert (off["answer"], on["answer"]) == ("", ""), report
    statuses = p["robot_status"]  # diagnostics_hz 0: only at level changes
    during = [s for s in statuses if off["start"] <= s[0] <= on["start"]]
    assert during and during[0][1] == 1, (statuses, report)  # WARN
    assert during[0][2].startswith("not ready: left_drive: SERVO A, START A"), statuses
    assert statuses[-1][1:] == [0, "ready"], statuses
    period = 1 / RATE_HZ
    for unit in robot.units:
        refused = dp0(out, unit, off["answered"] + period, on["start"])
        assert refused and all(a == 0 and b == 0 for _, a, b in refused), (unit, refused[:3])
        moving = dp0(out, unit, on["answered"], on["last"])
        assert any(a != 0 for _, a, _ in moving), (unit, "did not move again after ON")
    assert "input ros2:agv/cmd_vel refused: robot 'agv' may not move" in out["bridge_err"]
    stopped = [m for m in p["odom"] if off["answered"] + 0.5 < m[-1] < on["start"]]
    assert stopped and all((m[7], m[8]) == (0.0, 0.0) for m in stopped), report


@pytest.mark.wallclock  # real time: runtimes, sockets, processes
@pytest.mark.parametrize("transport", ["rclpy", "dds"])
def test_odom_tf_joint_states_and_joint_commands_against_real_rclpy(
    ros: tuple[str, Path, Path], tmp_path: Path, transport: str
) -> None:
    out = run(ros, tmp_path, transport)
    p, report = out["probe"], out["report"]
    assert p["matched"], report
    figures = check_odometry(out) | check_commands(out)
    if transport == "rclpy":
        check_refusal(out)
    print(f"{ros[0]} {transport}: {json.dumps(figures)}")  # the figures, with -s


def test_check_warns_of_two_robots_on_one_transform() -> None:
    """``abh3 check``: two robots with the same frame ids and odom_tf on put one transform
    on /tf twice; its own frame ids, odom_tf off or a /tf of its own each end it."""
    base = CONFIG.format(name="two", domain=0, transport="dds", distro="jazzy", timeout=300)
    second = (
        "  - name: agv2\n    track_m: 0.45\n    diameter_m: 0.2\n    gear_ratio: 20\n"
        "    pulses_per_rev: 4096\n    limits: {linear_mps: 0.8, angular_radps: 1.5}\n"
        "    wheels:\n      - {unit: l2, axis: A, side: left}\n"
        "      - {unit: r2, axis: A, side: right, sign: -1}\n"
    )
    units = (
        '  - {name: l2, abh3_id: 5, startup: ["SERVO ON ON"]}\n'
        '  - {name: r2, abh3_id: 6, startup: ["SERVO ON ON"]}\n'
    )
    text = base.replace("robots:\n  - name: agv", "robots:\n" + second + "  - name: agv")
    text = text.replace("robots:\n  - name: agv2", units + "robots:\n  - name: agv2", 1)
    said = warnings(parse_config(text, "two.yaml"))
    assert len(said) == 1, said
    line = text.splitlines().index("  - name: agv") + 1
    assert said[0].startswith(f"two.yaml:{line}: robots[1]: robot 'agv' publishes odom → "), said
    assert "as robot 'agv2' does" in said[0]
    own = text.replace("    frame_id: odom\n", "    frame_id: agv_odom\n")
    off = text.replace("agv: {joints:", "agv: {odom_tf: false, joints:")
    apart = text.replace(
        "    diagnostics_hz: 0", "    diagnostics_hz: 0\n    remap: {agv/tf: /agv/tf}"
    )
    for fixed in (own, off, apart):
        assert warnings(parse_config(fixed, "two.yaml")) == [], fixed


if __name__ == "__main__":  # pragma: no cover
    sys.exit(0)
