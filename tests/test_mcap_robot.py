"""``--record run.mcap`` of a robot on two drives, on the fake clock: one ``/<robot>/odom``
from every wheel (none per drive), at each round of its drives' DP0 replies (the command
rate, as the ROS 2 bridge publishes it: issue 51), following where the simulated robot
went, the covariance saying what each pose rests on."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

pytest.importorskip("mcap_ros2")
from mcap_ros2.reader import read_ros2_messages

from abh3_supervisor.config import parse_config
from abh3_supervisor.protocol import frames
from abh3_supervisor.runtime.mcap_recording import McapRecording
from abh3_supervisor.scheduler.core import FeedbackEvent
from tests.support.rig import Rig, set_twist
from tests.support.robot_truth import Truth

CONFIG = """
buses: {b: {interface: virtual, channel: mcap-robot, simulate: true}}
units:
  - {name: l, abh3_id: 1, broadcast: {mask: 0x13, rate_hz: 50}}
  - {name: r, abh3_id: 3, broadcast: {mask: 0x13, rate_hz: 20}}
  - {name: solo, abh3_id: 4, broadcast: {mask: 0x13, rate_hz: 25},
     geometry: {pulses_per_rev: 4096}}
robots:
  - name: rover
    track_m: 0.5
    diameter_m: 0.2
    gear_ratio: 10
    pulses_per_rev: 4096
    frame_id: world
    child_frame_id: rover_base
    wheels:
      - {unit: l, axis: A, side: left}
      - {unit: r, axis: A, side: right, sign: -1}
"""


def test_a_robots_odom_from_every_wheel_and_a_one_drive_robots_as_before(
    tmp_path: Path,
) -> None:
    config = parse_config(CONFIG, "robot.yaml")
    rig = Rig(config)
    path = tmp_path / "run.mcap"
    recording = McapRecording(path.open("wb"), config)
    recording.attach(rig.sup, rig.timeline.clock)
    rig.sup.subscribe(recording.observe)
    replies = {u: 0 for u in config.units}

    def count(event: object) -> None:
        if isinstance(event, FeedbackEvent) and not isinstance(event.reply, frames.Unknown):
            replies[event.unit] += 1

    rig.sup.subscribe(count)
    for unit in config.units:
        for command in ("SERVO ON ON", "START ON ON"):
            rig.sup.apply_text(unit, command)
    robot = config.robots["rover"]
    truth = Truth(robot, lambda unit, axis: float(rig.drive(unit).vel[axis]))
    rig.run(0.3)
    owner = rig.own("l")
    for i in range(3000):
        if i % 100 == 0 and i < 2000:
            set_twist(rig.sup, "rover", 0.3, -0.4, source=owner)
        if i == 2000:
            set_twist(rig.sup, "rover", 0.0, 0.0, source=owner)
        rig.run(0.001)
        truth.step(0.001)
    recording.stop()

    odom: dict[str, list[object]] = {}
    for m in read_ros2_messages(str(path)):
        if m.channel.topic.endswith("/odom"):
            odom.setdefault(m.channel.topic, []).append(m.ros_msg)
    assert set(odom) == {"/rover/odom", "/solo/odom"}  # none per drive of the robot
    # a pose per round of the drives' replies: each unit's once
    assert len(odom["/rover/odom"]) == pytest.approx(min(replies["l"], replies["r"]), abs=1)
    assert len(odom["/solo/odom"]) == replies["solo"]  # a one-drive robot: every reply
    # the pose rests on the counts (1e-6) at a round of them, else on the feedback since
    variances = {m.pose.covariance[0] for m in odom["/rover/odom"]}  # type: ignore[attr-defined]
    assert {1e-6, 1e-4} <= variances
    last = odom["/rover/odom"][-1]
    assert (last.header.frame_id, last.child_frame_id) == ("world", "rover_base")  # type: ignore[attr-defined]
    pose = last.pose.pose  # type: ignore[attr-defined]
    yaw = 2 * math.atan2(pose.orientation.z, pose.orientation.w)
    assert truth.yaw == pytest.approx(-0.4 * 2.0, rel=0.05)  # clockwise, as asked
    assert yaw == pytest.approx(truth.yaw, abs=0.01)
    assert (pose.position.x, pose.position.y) == pytest.approx((truth.x, truth.y), abs=0.005)
    solo = odom["/solo/odom"][-1]
    assert (solo.header.frame_id, solo.child_frame_id) == ("odom", "base_link")  # type: ignore[attr-defined]
