"""``ros_discovery_info``: the bridge as a node in the ROS 2 graph, over plain DDS.

ROS 2 learns which node owns which reader and writer from this topic, not from DDS
discovery: each participant publishes an ``rmw_dds_common/msg/ParticipantEntitiesInfo``
naming its nodes and, per node, the GIDs of their readers and writers. rmw_cyclonedds
takes an entity's GID from its DDS GUID (16 bytes, zero-padded to the GID's size), so
``ros2 node list``/``ros2 node info`` match our entities with what DDS discovered.

The participant GID is our own participant's, as rmw_cyclonedds announces it. Kilted's
rmw_fastrtps looks Cyclone endpoints up under an all-zero participant GID (Fast DDS 3.2.3
fills ``participant_guid`` only from a parameter Cyclone never sends), so its per-topic
info names them ``_CREATED_BY_BARE_DDS_APP_``; announcing the zero GID would fix that view
but leave a node behind in every graph after we exit (docs/ros2.md).

The GID's size differs by release, under one type name: ``char[24]`` in Humble,
``char[16]`` from Iron on (``discovery: humble`` or ``jazzy``, the default). Samples
of the other size do not decode, so a bridge set for the wrong release stays out of the
graph there (its topics still work). Iron and later also carry a type hash in each
endpoint's user data (``typehash=RIHS01_…``); we send none, which those releases accept
as unknown (``ros2 topic info -v`` shows it empty).
"""

# no `from __future__ import annotations`: cyclonedds reads the field types at runtime
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, sequence, uint8
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic

TOPIC = "ros_discovery_info"  # no rt/ prefix: rmw_dds_common avoids ROS's conventions
NODE_NAME = "abh3_supervisor"  # the rclpy transport's node name too
NODE_NAMESPACE = "/"
GID_SIZE = {"humble": 24, "jazzy": 16}  # Iron, Jazzy, Kilted, Rolling: 16
# what rmw_dds_common publishes it with: late joiners get the latest sample
QOS = Qos(
    Policy.Reliability.Reliable(0),
    Policy.Durability.TransientLocal,
    Policy.History.KeepLast(1),
)
# rmw_cyclonedds puts the participant's security enclave in its user data
PARTICIPANT_QOS = Qos(Policy.Userdata(b"enclave=/;"))


def _name(typ: str) -> str:
    return f"rmw_dds_common::msg::dds_::{typ}_"


def types_for(gid_size: int) -> tuple[Any, Any, Any]:
    """Gid, NodeEntitiesInfo and ParticipantEntitiesInfo with ``gid_size``-byte GIDs."""

    @dataclass
    class Gid(IdlStruct, typename=_name("Gid")):
        data: Annotated[Sequence[int], array(uint8, gid_size)] = field(
            default_factory=lambda: [0] * gid_size
        )

    @dataclass
    class NodeEntitiesInfo(IdlStruct, typename=_name("NodeEntitiesInfo")):
        node_namespace: str = ""
        node_name: str = ""
        reader_gid_seq: Annotated[Sequence[Gid], sequence(Gid)] = field(default_factory=list)
        writer_gid_seq: Annotated[Sequence[Gid], sequence(Gid)] = field(default_factory=list)

    @dataclass
    class ParticipantEntitiesInfo(IdlStruct, typename=_name("ParticipantEntitiesInfo")):
        gid: Gid = field(default_factory=Gid)
        node_entities_info_seq: Annotated[
            Sequence[NodeEntitiesInfo], sequence(NodeEntitiesInfo)
        ] = field(default_factory=list)

    return Gid, NodeEntitiesInfo, ParticipantEntitiesInfo


TYPES = {release: types_for(size) for release, size in GID_SIZE.items()}


def gid_bytes(entity: Any, size: int) -> list[int]:
    """An entity's GID as rmw_cyclonedds makes it: its 16-byte DDS GUID, zero-padded."""
    return list(entity.guid.bytes.ljust(size, b"\0"))


class Announcer:
    """Publishes the participant's one node and its entities (again when they change)."""

    def __init__(self, participant: DomainParticipant, release: str) -> None:
        self.participant, self.size = participant, GID_SIZE[release]
        self.gid, self.node, self.info = TYPES[release]
        self.writer: DataWriter[Any] = DataWriter(
            participant, Topic(participant, TOPIC, self.info), qos=QOS
        )

    def message(self, readers: Iterable[Any], writers: Iterable[Any]) -> Any:
        node = self.node(
            node_namespace=NODE_NAMESPACE,
            node_name=NODE_NAME,
            reader_gid_seq=[self.gid(gid_bytes(r, self.size)) for r in readers],
            writer_gid_seq=[self.gid(gid_bytes(w, self.size)) for w in writers],
        )
        return self.info(self.gid(gid_bytes(self.participant, self.size)), [node])

    def announce(self, readers: Iterable[Any], writers: Iterable[Any]) -> None:
        self.writer.write(self.message(readers, writers))
