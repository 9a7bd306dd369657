"""docs/nav2.md and its example (issue 51): the example AGV file is what `abh3 check`
accepts without a warning, with the robot the document describes; the YAML blocks of
docs/nav2.md and the ros2_control block of docs/ros2.md are valid."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

pytest.importorskip("cyclonedds")
from abh3_supervisor.config import parse_config
from abh3_supervisor.config.advice import odometry, warnings
from abh3_supervisor.plugin_host.host import PluginHost

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "docs" / "examples" / "nav2" / "agv.yaml"


def test_the_example_agv_is_accepted_without_a_warning_and_is_the_documented_robot() -> None:
    config = parse_config(EXAMPLE.read_text(), str(EXAMPLE))
    PluginHost(config)  # the ros2 section too: raises on any problem
    assert warnings(config) == []
    agv = config.robots["agv"]
    assert agv.track_m == 0.45 and len(agv.units) == 2
    assert {(w.diameter_m, w.gear_ratio, w.pulses_per_rev) for w in agv.wheels} == {
        (0.2, 20.0, 4096.0)
    }
    (line,) = odometry(config)
    assert line in (ROOT / "docs" / "nav2.md").read_text()  # the line the document shows


def test_the_yaml_blocks_of_the_nav2_document_are_valid_plugin_sections() -> None:
    text = (ROOT / "docs" / "nav2.md").read_text()
    blocks = re.findall(r"```yaml\n(.*?)```", text, re.S)
    assert blocks
    base = EXAMPLE.read_text().split("plugins:")[0]
    for block in blocks:
        PluginHost(parse_config(base + block, "docs/nav2.md"))


def test_the_ros2_control_block_names_the_robots_topics_and_its_controller_its_geometry() -> None:
    text = (ROOT / "docs" / "ros2.md").read_text()
    (xml,) = re.findall(r"```xml\n(.*?)```", text, re.S)
    assert '<param name="joint_states_topic">/agv/joint_states</param>' in xml
    assert '<param name="joint_commands_topic">/agv/joint_commands</param>' in xml
    config = parse_config(EXAMPLE.read_text(), str(EXAMPLE))
    joints = config.plugins["ros2"]["robots"]["agv"]["joints"]
    for name in joints.values():
        assert f'<joint name="{name}">' in xml
    controllers = next(
        yaml.safe_load(b)
        for b in re.findall(r"```yaml[^\n]*\n(.*?)```", text, re.S)
        if "diff_drive_controller" in b
    )
    p = controllers["diff_drive_controller"]["ros__parameters"]
    agv = config.robots["agv"]
    assert (p["wheel_separation"], p["wheel_radius"]) == (agv.track_m, agv.wheels[0].diameter_m / 2)
