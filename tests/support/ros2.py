"""Another ROS 2 participant in this process and ``abh3 run`` with the ROS 2 plugin in a
child process, over DDS on loopback (multicast off)."""

from __future__ import annotations

import itertools
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("cyclonedds")
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from abh3_plugins.ros2 import types
from abh3_plugins.ros2.dds import LOOPBACK_URI, SERVICE_QOS, qos
from abh3_plugins.ros2.settings import QosSettings

ROOT = Path(__file__).resolve().parent.parent.parent

ROS_DEFAULT = qos(QosSettings())


UNIT = """
buses:
  demo: {{interface: virtual, channel: ros2-{domain}, simulate: true}}
units:
  - name: left
    abh3_id: 1
    broadcast: {{mask: 0x13, rate_hz: 20}}
    geometry: {{pulses_per_rev: 4096}}
    startup: {startup}
plugins:
  ros2: {{domain_id: {domain}{extra}}}
"""


_client = itertools.count(1)


class Peer:
    """The other ROS 2 participant: topics under /left, and an inp_service client."""

    def __init__(self, domain: int) -> None:
        self.dp = DomainParticipant(domain)
        self.topics: dict[str, Topic[Any]] = {}
        self.guid, self.sequence = next(_client) << 32, 0
        # service name → its request writer and reply reader (inp_service, enable)
        self.services: dict[str, tuple[DataWriter[Any], DataReader[Any]]] = {}

    def _service(self, name: str) -> tuple[DataWriter[Any], DataReader[Any]]:
        if name not in self.services:
            request = DataWriter(
                self.dp,
                Topic(self.dp, f"rq/left/{name}Request", types.Abh3InputRequest),
                qos=SERVICE_QOS,
            )
            reply = DataReader(
                self.dp,
                Topic(self.dp, f"rr/left/{name}Reply", types.Abh3InputResponse),
                qos=SERVICE_QOS,
            )
            self.services[name] = (request, reply)
        return self.services[name]

    def _topic(self, name: str, typ: type) -> Topic[Any]:
        if name not in self.topics:
            self.topics[name] = Topic(self.dp, f"rt/left/{name}", typ)
        return self.topics[name]

    def reader(self, name: str, typ: type) -> DataReader[Any]:
        return DataReader(self.dp, self._topic(name, typ), qos=ROS_DEFAULT)

    def writer(self, name: str, typ: type) -> DataWriter[Any]:
        return DataWriter(self.dp, self._topic(name, typ), qos=ROS_DEFAULT)

    def call(self, command: str, seconds: float = 20, service: str = "inp_service") -> str | None:
        """A service (inp_service, or the robot's enable) as a ROS client calls it: resend
        until the service is matched."""
        request, replies = self._service(service)
        self.sequence += 1
        for _ in range(int(seconds / 0.5)):
            request.write(types.Abh3InputRequest(self.guid, self.sequence, command))
            for reply in replies.take_iter(timeout=duration(milliseconds=500)):
                if (reply.client_guid, reply.sequence) == (self.guid, self.sequence):
                    return str(reply.responce)
        return None


@pytest.fixture
def supervisor(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Any]:
    """Start ``abh3 run`` with a config; yields a starter; checks the clean stop after."""
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK_URI)
    procs: list[subprocess.Popen[str]] = []

    def start(domain: int, startup: str = "[]", extra: str = "") -> Peer:
        cfg = tmp_path / "ros2.yaml"
        cfg.write_text(UNIT.format(domain=domain, startup=startup, extra=extra))
        command = [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless"]
        procs.append(
            subprocess.Popen(
                [*command, "--duration", "60"], stderr=subprocess.PIPE, text=True, cwd=ROOT
            )
        )
        return Peer(domain)

    yield start
    for proc in procs:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert "stop frame confirmed" in err
        assert "Traceback" not in err
