"""The bridge in the ROS 2 graph: ``ros_discovery_info`` with the right GIDs, and
``/diagnostics`` reaching another process, over plain DDS (loopback only, multicast off).

The other participant is independent of the bridge's code for what it checks: it learns
the supervisor's endpoints from DDS's own discovery (the builtin publication and
subscription topics, whose keys are the endpoints' GUIDs as they went over the wire) and
holds the GIDs the bridge announces against them, as ``ros2 node info`` does.
"""

from __future__ import annotations

import uuid
from typing import Any

import pytest

pytest.importorskip("cyclonedds")
from cyclonedds.builtin import (
    BuiltinDataReader,
    BuiltinTopicDcpsPublication,
    BuiltinTopicDcpsSubscription,
)
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from rosbags.typesys import Stores, get_typestore

from abh3_plugins.ros2 import discovery, types
from tests.support.ros2 import ROS_DEFAULT, supervisor  # noqa: F401  (the fixture)


@pytest.mark.parametrize(
    ("release", "store"), [("humble", Stores.ROS2_HUMBLE), ("jazzy", Stores.ROS2_JAZZY)]
)
def test_the_message_bytes_match_rosbags_rmw_dds_common_of_that_release(
    release: str, store: Stores
) -> None:
    np = pytest.importorskip("numpy")
    gid_t, node_t, info_t = discovery.TYPES[release]
    size = discovery.GID_SIZE[release]
    gid = [(i * 37) % 256 for i in range(16)] + [0] * (size - 16)
    ours = info_t(
        gid_t(gid), [node_t("/", "abh3_supervisor", [gid_t(gid)], [gid_t(gid), gid_t(gid)])]
    )
    ts = get_typestore(store)
    t = ts.types
    g = t["rmw_dds_common/msg/Gid"](np.array(gid, dtype=np.uint8))
    theirs = t["rmw_dds_common/msg/ParticipantEntitiesInfo"](
        g, [t["rmw_dds_common/msg/NodeEntitiesInfo"]("/", "abh3_supervisor", [g], [g, g])]
    )
    assert ours.serialize() == bytes(
        ts.serialize_cdr(theirs, "rmw_dds_common/msg/ParticipantEntitiesInfo")
    )
    assert info_t.__idl_typename__ == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"


def _guid(data: Any) -> uuid.UUID:
    return uuid.UUID(bytes=bytes(data[:16]))


@pytest.mark.wallclock
def test_the_node_and_its_entities_are_in_ros_discovery_info_with_their_dds_guids(
    supervisor: Any,  # noqa: F811
) -> None:
    peer = supervisor(21, extra=", allow_commands: true")
    dp = peer.dp
    _, _, info_t = discovery.TYPES["jazzy"]
    infos: DataReader[Any] = DataReader(dp, Topic(dp, discovery.TOPIC, info_t), qos=discovery.QOS)
    ours = None
    for sample in infos.take_iter(timeout=duration(seconds=20)):
        if any(n.node_name == "abh3_supervisor" for n in sample.node_entities_info_seq):
            ours = sample
            break
    assert ours is not None, "no ros_discovery_info from the bridge"
    participant = _guid(ours.gid.data)
    assert bytes(ours.gid.data[16:]) == b""  # jazzy: 16-byte GIDs
    (node,) = ours.node_entities_info_seq
    assert (node.node_namespace, node.node_name) == ("/", "abh3_supervisor")
    announced_writers = {_guid(g.data) for g in node.writer_gid_seq}
    announced_readers = {_guid(g.data) for g in node.reader_gid_seq}
    # feedback 2, brd0/1/4 (mask 0x13), odom, tf, joint_states, conversions 6, the two
    # services' replies (inp_service, the robot's enable), diagnostics
    assert len(announced_writers) == 17
    # brd_num, xa/yx/ab, vel_cmd, cur_cmd, cmd_vel, joint_commands, inp_data, the two
    # services' requests
    assert len(announced_readers) == 11

    # what DDS discovery says the supervisor's participant has, keyed by endpoint GUID
    wire: dict[str, dict[uuid.UUID, str]] = {"pub": {}, "sub": {}}
    readers = {
        "pub": BuiltinDataReader(dp, BuiltinTopicDcpsPublication),
        "sub": BuiltinDataReader(dp, BuiltinTopicDcpsSubscription),
    }
    for _ in range(40):  # each take waits for data; stops once every GID is seen
        for kind, reader in readers.items():
            for ep in reader.take_iter(timeout=duration(milliseconds=250)):
                if ep.participant_key == participant:
                    wire[kind][ep.key] = ep.topic_name
        if announced_writers <= set(wire["pub"]) and announced_readers <= set(wire["sub"]):
            break
    writers = {k: t for k, t in wire["pub"].items() if t != discovery.TOPIC}
    assert set(writers) == announced_writers
    assert set(wire["sub"]) == announced_readers
    topics = set(writers.values()) | set(wire["sub"].values())
    assert {
        "rt/left/vel_fbk_ab",
        "rt/left/brd0_data",
        "rt/left/odom",
        "rt/tf",
        "rt/left/joint_states",
        "rt/left/joint_commands",
        "rt/diagnostics",
        "rt/left/vel_cmd",
        "rt/left/cmd_vel",
        "rq/left/inp_serviceRequest",
        "rr/left/inp_serviceReply",
    } <= topics

    # and /diagnostics from the other process: a bus and a unit, the unit online
    diagnostics = DataReader(
        dp, Topic(dp, "rt/diagnostics", types.DiagnosticArray), qos=ROS_DEFAULT
    )
    for array in diagnostics.take_iter(timeout=duration(seconds=10)):
        status = {s.name: s for s in array.status}
        if status["abh3_supervisor: unit left"].message == "online":
            assert status["abh3_supervisor: unit left"].level == 0
            assert "abh3_supervisor: bus demo" in status
            break
    else:
        pytest.fail("no /diagnostics with the unit online")
