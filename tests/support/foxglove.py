"""The Foxglove tests' configuration: two simulated units, one moving, served live on any
free loopback port (tests/test_foxglove.py, tests/test_watchers_foxglove.py)."""

from __future__ import annotations

from abh3_supervisor.config import Config, parse_config

CONFIG = """
buses:
  demo: {interface: virtual, channel: foxglove-test, simulate: true}
units:
  - name: left
    abh3_id: 1
    velocity_model: motor
    command_rate_hz: 100
    broadcast: {mask: 0x7f, rate_hz: 14}
    geometry: {pulses_per_rev: 4096}
    startup: ["SERVO ON ON", "START ON ON", "VEL 120 -80"]
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor, command_rate_hz: 100,
     broadcast: {mask: 0x0f, rate_hz: 8}}
foxglove: 127.0.0.1:0
"""


def config(text: str = CONFIG) -> Config:
    return parse_config(text, "foxglove.yaml")
