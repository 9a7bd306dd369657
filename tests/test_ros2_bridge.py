"""The ROS 2 bridge between two processes over DDS, loopback only, multicast off."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds")
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from abh3_plugins.ros2 import types
from abh3_plugins.ros2.bridge import ROS_DEFAULT, twist
from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.kinematics import Geometry, twist_to_ab
from abh3_supervisor.plugin_host import PluginHost

ROOT = Path(__file__).resolve().parent.parent
DOMAIN = 17
LOOPBACK = (
    "<CycloneDDS><Domain Id='any'><General><Interfaces><NetworkInterface address='127.0.0.1'/>"
    "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
    "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>30</MaxAutoParticipantIndex>"
    "<Peers><Peer address='127.0.0.1'/></Peers></Discovery></Domain></CycloneDDS>"
)
CONFIG = f"""
buses:
  demo: {{interface: virtual, channel: ros2-test, simulate: true}}
units:
  - name: left
    abh3_id: 1
    broadcast: {{mask: 0x03, rate_hz: 20}}
    startup: ["SERVO ON ON", "START ON ON", "VEL 300 20"]
plugins:
  ros2: {{domain_id: {DOMAIN}}}
"""


def test_commands_stay_off_unless_implemented_and_enabled() -> None:
    cfg = parse_config(CONFIG.replace(f"domain_id: {DOMAIN}", "allow_commands: true"), "r.yaml")
    with pytest.raises(ConfigError, match="commands over ROS 2 are not implemented yet"):
        PluginHost(cfg)


def test_feedback_status_and_conversions_reach_another_process(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    cfg = tmp_path / "ros2.yaml"
    cfg.write_text(CONFIG)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "abh3_supervisor",
            "run",
            str(cfg),
            "--headless",
            "--duration",
            "30",
        ],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        dp = DomainParticipant(DOMAIN)

        def reader(name: str, typ: type) -> DataReader:  # type: ignore[type-arg]
            return DataReader(dp, Topic(dp, f"rt/left/{name}", typ), qos=ROS_DEFAULT)

        fbk_ab, fbk_yx = (
            reader("vel_fbk_ab", types.Abh3Velocity),
            reader("vel_fbk_yx", types.Abh3Velocity),
        )
        brd1, xa_ab = reader("brd1_data", types.Abh3Brd1), reader("xa_ab", types.Abh3Velocity)
        xa = DataWriter(dp, Topic(dp, "rt/left/xa", types.Twist), qos=ROS_DEFAULT)

        def until(reader: DataReader, want: object, seconds: float = 20) -> bool:  # type: ignore[type-arg]
            for sample in reader.take_iter(timeout=duration(seconds=seconds)):  # waits on data
                if sample == want:
                    return True
            return False

        # the drive ramps to the command: Y 300, X 20 = A 320, B 280 at the motors
        assert until(fbk_ab, types.Abh3Velocity(320.0, 280.0))
        assert until(fbk_yx, types.Abh3Velocity(300.0, 20.0), 5)
        control = next(brd1.take_iter(timeout=duration(seconds=5)))
        assert control.control & 0x3 == 0x3  # servo and start on, as the drive reports
        for _ in range(20):  # until the bridge's reader is matched and answers
            xa.write(twist(0.5, 0.2))
            answers = list(xa_ab.take_iter(timeout=duration(milliseconds=500)))
            if answers:
                break
        a, b = twist_to_ab(0.5, 0.2, Geometry())
        assert (answers[0].vel_ay, answers[0].vel_bx) == (pytest.approx(a), pytest.approx(b))
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stop frame confirmed" in err
