"""ROS 2 over plain DDS with cyclonedds, no ROS install: ROS 2's naming and wire format.

Topics are ``rt<name>``; a service is a request topic ``rq<name>Request`` and a reply
topic ``rr<name>Reply`` whose samples start with rmw_cyclonedds's request header (client
GUID, sequence number), echoed in the reply so the calling client recognises it.

One thread per participant waits on a WaitSet and takes samples itself. No cyclonedds
listener callbacks: those run on the middleware's threads while it holds its own locks,
and a Python callback there can deadlock against a write from another Python thread.
Replies computed elsewhere (a drive's answer) are handed back to this thread to write.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import os
import threading
from collections.abc import Callable
from typing import Any

from cyclonedds.core import GuardCondition, Policy, Qos, ReadCondition, SampleState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from abh3_plugins.ros2 import discovery, types
from abh3_plugins.ros2.dds_write import packed_write
from abh3_plugins.ros2.settings import QosSettings, Settings
from abh3_plugins.ros2.transport import Publish, ServiceHandler
from abh3_supervisor.plugin_api import RESPONSE_INVALID

log = logging.getLogger(__name__)
TAKE = 64  # samples per reader per wake-up; more stay triggered for the next round


def qos(q: QosSettings) -> Qos:
    reliability = (
        Policy.Reliability.Reliable(duration(milliseconds=100))
        if q.reliability == "reliable"
        else Policy.Reliability.BestEffort
    )
    durability = (
        Policy.Durability.TransientLocal
        if q.durability == "transient_local"
        else Policy.Durability.Volatile
    )
    return Qos(reliability, durability, Policy.History.KeepLast(q.depth))


# a CYCLONEDDS_URI that keeps DDS on this machine: loopback only, multicast off, 127.0.0.1
# the only peer: what the tests and the benchmarks run on
LOOPBACK_URI = (
    "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/>"
    "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
    "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>"
    "<Peers><Peer address='127.0.0.1'/></Peers></Discovery></Domain></CycloneDDS>"
)
# Fast DDS 3 (Kilted and later) announces XTypes type information for every endpoint. Cyclone
# DDS then asks for the type objects, cannot make all of them out, and never matches our
# writers to those readers: nothing we publish arrives. ROS 2 does not match on that
# information either (it compares type names, and its own type hashes in the user data),
# so ignore eProsima's (vendor id 1.15) and match by type name, as with Fast DDS 2 (Jazzy)
# and rmw_cyclonedds. Merged after the user's CYCLONEDDS_URI, so it holds with theirs.
COMPATIBILITY = (
    "<CycloneDDS><Domain Id='any'><Compatibility>"
    "<IgnoreTypeInformation>1.15</IgnoreTypeInformation>"
    "</Compatibility></Domain></CycloneDDS>"
)
_domains: dict[int, Domain] = {}  # one per domain id and process, alive as long as it


def domain(domain_id: int) -> Domain:
    """The DDS domain with the user's configuration plus :data:`COMPATIBILITY`."""
    found = _domains.get(domain_id)
    if found is None:
        user = os.environ.get("CYCLONEDDS_URI", "").strip()
        config = f"{user},{COMPATIBILITY}" if user else COMPATIBILITY
        found = _domains[domain_id] = Domain(domain_id, config)
    return found


# ROS 2's services default: reliable, volatile, keep the last 10
SERVICE_QOS = qos(QosSettings())


class DdsTransport:
    msg = types

    def __init__(self, settings: Settings) -> None:
        self.domain = domain(settings.domain_id)
        self.participant = DomainParticipant(settings.domain_id, qos=discovery.PARTICIPANT_QOS)
        self.announcer = (
            discovery.Announcer(self.participant, settings.discovery)
            if settings.discovery != "off"
            else None
        )
        self.writers: list[DataWriter[Any]] = []  # the node's entities, for ros_discovery_info
        self.qos = qos(settings.qos)
        self.waitset = WaitSet(self.participant)
        self.wake = GuardCondition(self.participant)
        self.waitset.attach(self.wake)
        self._readers: list[tuple[DataReader[Any], Callable[[Any], None]]] = []
        self._topics: dict[str, Topic[Any]] = {}
        self._outbox: collections.deque[Callable[[], None]] = collections.deque()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="ros2-dds", daemon=True)

    def _topic(self, name: str, typ: type) -> Topic[Any]:
        topic = self._topics.get(name)
        if topic is None:  # one topic entity per name, shared by readers and writers
            topic = self._topics[name] = Topic(self.participant, name, typ)
        return topic

    def publisher(self, name: str, typ: type) -> Publish:
        writer = DataWriter(self.participant, self._topic(f"rt{name}", typ), qos=self.qos)
        self.writers.append(writer)
        return packed_write(writer, typ)  # a flat message in one pack (dds_write.py)

    def subscribe(self, name: str, typ: type, handle: Callable[[Any], None]) -> None:
        self._reader(f"rt{name}", typ, handle, self.qos)

    def serve(self, name: str, handle: ServiceHandler) -> None:
        reply = DataWriter(
            self.participant,
            self._topic(f"rr{name}Reply", types.Abh3InputResponse),
            qos=SERVICE_QOS,
        )
        self.writers.append(reply)

        def answer(request: types.Abh3InputRequest, done: concurrent.futures.Future[str]) -> None:
            try:
                text = done.result()
            except Exception:
                log.exception("ros2: %s: the command failed", name)
                text = RESPONSE_INVALID
            reply.write(types.Abh3InputResponse(request.client_guid, request.sequence, text))

        def on_request(request: types.Abh3InputRequest) -> None:
            future = handle(request.command)
            future.add_done_callback(lambda f: self._post(lambda: answer(request, f)))

        self._reader(f"rq{name}Request", types.Abh3InputRequest, on_request, SERVICE_QOS)

    def _reader(self, topic: str, typ: type, handle: Callable[[Any], None], q: Qos) -> None:
        reader = DataReader(self.participant, self._topic(topic, typ), qos=q)
        self.waitset.attach(ReadCondition(reader, SampleState.NotRead))
        self._readers.append((reader, handle))

    def _post(self, action: Callable[[], None]) -> None:
        """Run ``action`` on the transport's thread (from any thread)."""
        self._outbox.append(action)
        self.wake.set(True)

    def start(self) -> None:
        if self.announcer is not None:  # every entity exists now: the node as it stays
            self.announcer.announce([r for r, _ in self._readers], self.writers)
        self._thread.start()

    def _run(self) -> None:
        while not self._closing:
            self.waitset.wait(duration(seconds=1))
            self.wake.set(False)
            for reader, handle in self._readers:
                for sample in reader.take(N=TAKE):
                    if not isinstance(sample, InvalidSample):  # a writer went away
                        self._call(handle, sample)
            while self._outbox:
                self._call(self._outbox.popleft())

    @staticmethod
    def _call(fn: Callable[..., None], *args: Any) -> None:
        try:
            fn(*args)
        except Exception:  # a bad sample must not end the bridge
            log.exception("ros2: handling a sample failed")

    def close(self) -> None:
        self._closing = True
        self.wake.set(True)
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        self._readers.clear()
        # cyclonedds deletes the entities with the participant when it is collected
