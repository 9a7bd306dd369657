"""The ROS 2 bridge between two processes over DDS, loopback only, multicast off.

The supervisor runs as ``abh3 run`` in a child process on the simulated drives; this
process is the other ROS 2 participant, speaking plain DDS with ROS 2's naming, as a ROS
node on rmw_cyclonedds would. Each test uses a domain of its own.
"""

from __future__ import annotations

import math
from typing import Any

import pytest

pytest.importorskip("cyclonedds")
from cyclonedds.sub import DataReader
from cyclonedds.util import duration

from abh3_plugins.ros2 import types
from abh3_plugins.ros2.bridge import twist
from abh3_supervisor.core.kinematics import Geometry, twist_to_ab, twist_to_yx
from tests.support import ros2

pytestmark = pytest.mark.wallclock  # real time: runtimes, sockets, processes

supervisor = ros2.supervisor  # the fixture: `abh3 run` and a peer


def until(reader: DataReader[Any], want: Any, seconds: float = 20) -> Any:
    """The first sample equal to ``want`` (or for which ``want`` is true), or None."""
    for sample in reader.take_iter(timeout=duration(seconds=seconds)):  # waits on data
        if want(sample) if callable(want) else sample == want:
            return sample
    return None


def close(a: types.Abh3Velocity, ay: float, bx: float, tol: float = 0.3) -> bool:
    return abs(a.vel_ay - ay) <= tol and abs(a.vel_bx - bx) <= tol


def test_feedback_status_odometry_and_conversions_reach_another_process(
    supervisor: Any,
) -> None:
    peer = supervisor(17, startup='["SERVO ON ON", "START ON ON", "VEL 300 20"]')
    fbk_ab = peer.reader("vel_fbk_ab", types.Abh3Velocity)
    fbk_yx = peer.reader("vel_fbk_yx", types.Abh3Velocity)
    brd1 = peer.reader("brd1_data", types.Abh3Brd1)
    odom = peer.reader("odom", types.Odometry)
    xa_ab = peer.reader("xa_ab", types.Abh3Velocity)
    xa = peer.writer("xa", types.Twist)
    vel_cmd = peer.writer("vel_cmd", types.Abh3Velocity)
    # the drive ramps to the command: Y 300, X 20 = A 320, B 280 at the motors
    assert until(fbk_ab, types.Abh3Velocity(320.0, 280.0))
    assert until(fbk_yx, types.Abh3Velocity(300.0, 20.0), 5)
    # servo and start on, as the drive reports (the reader may still hold a packet from
    # before the start-up commands took effect: the first one that says so)
    assert until(brd1, lambda b: b.control & 0x3 == 0x3, 5)
    # odometry: the twist from the feedback, the pose from the pulse counts
    speed = (300 / 60 * 0.1 * 0.1 * math.pi, -20 / 60 * 0.1 * 0.1 * math.pi / 0.25)
    first = until(
        odom,
        lambda o: [o.twist.twist.linear.x, o.twist.twist.angular.z] == pytest.approx(speed),
        5,
    )
    assert first is not None
    assert (first.header.frame_id, first.child_frame_id) == ("odom", "base_link")
    assert until(odom, lambda o: o.pose.pose.position.x > first.pose.pose.position.x + 0.01)
    for _ in range(20):  # until the bridge's reader is matched and answers
        xa.write(twist(types, 0.5, 0.2))
        vel_cmd.write(types.Abh3Velocity(-500.0, 0.0))  # commands are off by default
        answers = list(xa_ab.take_iter(timeout=duration(milliseconds=500)))
        if answers:
            break
    a, b = twist_to_ab(0.5, 0.2, Geometry())
    assert (answers[0].vel_ay, answers[0].vel_bx) == (pytest.approx(a), pytest.approx(b))
    # the seed's formulas: Y = v·60/(r·wheel·π), X = −ω·60/(r·wheel·π)·width/2
    k = 60 / (0.1 * 0.1 * math.pi)
    assert [a, b] == pytest.approx([0.5 * k - 0.2 * k * 0.25, 0.5 * k + 0.2 * k * 0.25])
    assert until(fbk_ab, types.Abh3Velocity(320.0, 280.0), 2)  # vel_cmd changed nothing
    assert peer.call("SERVO OFF OFF", seconds=2) is None  # no service without allow_commands


def test_commands_service_and_staleness_across_processes(supervisor: Any) -> None:
    """The issue's check: vel_cmd drives, inp_service answers as the seed, silence → zero."""
    peer = supervisor(18, extra=", allow_commands: true, command_timeout_ms: 300")
    fbk_ab = peer.reader("vel_fbk_ab", types.Abh3Velocity)
    fbk_yx = peer.reader("vel_fbk_yx", types.Abh3Velocity)
    vel_cmd = peer.writer("vel_cmd", types.Abh3Velocity)
    cmd_vel = peer.writer("cmd_vel", types.Twist)
    assert peer.call("SERVO ON ON") == ""
    assert peer.call("FOO") == "Invalid Command."
    assert peer.call("START ON ON") == ""
    # the robot's enable service: off, on (answered once every drive reports it), junk
    assert peer.call("OFF", service="enable") == ""
    assert peer.call("ON", service="enable") == ""
    assert peer.call("maybe", service="enable") == "Invalid Command."

    def drive(write: Any, sample: Any, reader: DataReader[Any], want: Any) -> bool:
        """Publish at 20 Hz, as a teleop node does, until the feedback shows ``want``."""
        for _ in range(200):
            write(sample)
            for got in reader.take_iter(timeout=duration(milliseconds=50)):
                if want(got):
                    return True
        return False

    vel_cmd.write(types.Abh3Velocity(math.nan, 0.0))  # refused, never reaches a drive
    vel_cmd.write(types.Abh3Velocity(1e9, 0.0))
    assert drive(
        vel_cmd.write, types.Abh3Velocity(300.0, 20.0), fbk_yx, lambda m: close(m, 300, 20)
    )
    assert until(fbk_ab, lambda m: close(m, 320, 280), 5)
    # silence longer than command_timeout_ms: the unit is zeroed and the drive ramps down
    assert until(fbk_ab, types.Abh3Velocity(0.0, 0.0), 10)
    y, x = twist_to_yx(0.2, 0.5, Geometry())
    assert drive(cmd_vel.write, twist(types, 0.2, 0.5), fbk_yx, lambda m: close(m, y, x, 0.2))
    assert peer.call("SERVO OFF OFF") == ""


def test_brd_num_asks_the_drive_for_packets_of_the_mask(supervisor: Any) -> None:
    """status: request is the seed's status node: a packet only when brd_num asks for it."""
    peer = supervisor(19, extra=", status: request")
    brd0 = peer.reader("brd0_data", types.Abh3Brd0)
    brd4 = peer.reader("brd4_data", types.Abh3Brd4)
    brd_num = peer.writer("brd_num", types.Int32)
    got: list[Any] = []
    for _ in range(40):
        brd_num.write(types.Int32(4))
        brd_num.write(types.Int32(2))  # outside the mask 0x13: ignored, as the seed does
        got = list(brd4.take_iter(timeout=duration(milliseconds=500)))
        if got:
            break
    assert got and isinstance(got[0], types.Abh3Brd4)
    # the unit polls 0, 1 and 4 by itself, but with status: request only asked ones go out
    assert list(brd0.take_iter(timeout=duration(seconds=1))) == []
