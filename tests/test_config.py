"""YAML configuration: defaults, and every error naming file, line and key."""

from __future__ import annotations

from pathlib import Path

import pytest

from abh3_supervisor.cli import main
from abh3_supervisor.config import ControlMode, Role, VelocityModel, load_config, parse_config
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.protocol.frames import Generation

ROOT = Path(__file__).resolve().parent.parent
MINIMAL = "buses:\n  can0: {}\nunits:\n  - name: drive\n"


def problems(text: str) -> list[str]:
    with pytest.raises(ConfigError) as info:
        parse_config(text, "robot.yaml")
    return info.value.problems


def test_defaults_are_the_seeds() -> None:
    cfg = parse_config(MINIMAL, "m.yaml")
    bus = cfg.buses["can0"]
    assert (bus.interface, bus.channel, bus.bitrate, bus.simulate) == (
        "socketcan",
        "can0",
        500000,
        None,
    )
    u = cfg.units["drive"]
    assert (u.bus, u.abh3_id, u.host_id, u.priority, u.brd_group, u.timeout_ms) == (
        "can0",
        1,
        2,
        0,
        5,
        1000,
    )
    assert u.broadcast.mask == 0x7F and u.broadcast.packets == (0, 1, 2, 3, 4, 5, 6)
    assert u.protocol is Generation.G2021 and u.control is ControlMode.VELOCITY
    assert u.velocity_model is VelocityModel.TRAVEL and u.role is Role.COMMAND
    g = u.geometry
    assert (g.rate_num, g.rate_den, g.wheel, g.width) == (1.0, 10.0, 0.1, 0.5)


def test_shipped_configs_are_valid() -> None:
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        assert load_config(path).units, path


def test_everything_set() -> None:
    cfg = parse_config(
        """
buses:
  left_bus: {interface: virtual, channel: x, bitrate: 1000000, options: {rx_queue_size: 10},
             simulate: {command_zero_timeout_ms: 0, accel: 500}}
units:
  - name: m
    abh3_id: 253
    host_id: 0
    priority: 7
    brd_group: 31
    protocol: "2023"
    timeout_ms: 200
    command_rate_hz: 100
    control: current
    velocity_model: motor
    role: monitor
    broadcast: {mask: 3, rate_hz: 2.5, listen_only: true}
    geometry: {rate_num: 1, rate_den: 20, wheel: 0.2, width: 0.4}
    limits: {velocity: 1000, current: 50}
    data_select: {ay: 6, bx: 5}
    startup: ["SERVO ON ON"]
plugins:
  csv: {path: out.csv}
""",
        "full.yaml",
    )
    u = cfg.units["m"]
    assert (u.abh3_id, u.host_id, u.priority, u.brd_group, u.protocol) == (
        253,
        0,
        7,
        31,
        Generation.G2023,
    )
    assert u.broadcast.packets == (0, 1) and u.broadcast.listen_only
    assert u.limits.velocity == 1000 and u.data_select == (6, 5) and u.role is Role.MONITOR
    bus = cfg.buses["left_bus"]
    assert bus.options == {"rx_queue_size": 10}
    assert bus.simulate is not None and bus.simulate.accel == 500
    assert cfg.plugins == {"csv": {"path": "out.csv"}} and cfg.plugin_lines == {"csv": 23}


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("buses: [", "robot.yaml:1: invalid YAML"),
        ("units: []\n", "robot.yaml:1: buses: missing"),
        (
            MINIMAL + "    abh3_idd: 3\n",
            "robot.yaml:5: units[0].abh3_idd: unknown key; did you mean 'abh3_id'?",
        ),
        (
            MINIMAL + "    abh3_id: 254\n",
            "robot.yaml:5: units[0].abh3_id: 254 is out of range (allowed 0–253)",
        ),
        (MINIMAL + "    host_id: -1\n", "units[0].host_id: -1 is out of range (allowed 0–253)"),
        (MINIMAL + "    priority: 8\n", "units[0].priority: 8 is out of range (allowed 0–7)"),
        (MINIMAL + "    brd_group: 32\n", "units[0].brd_group: 32 is out of range (allowed 0–31)"),
        (MINIMAL + "    broadcast: {mask: 0x80}\n", "units[0].broadcast.mask: 128 is out of range"),
        (
            MINIMAL + "    command_rate_hz: 0\n",
            "command_rate_hz: 0 is out of range (allowed more than 0, up to 1000)",
        ),
        (MINIMAL + "    command_rate_hz: .nan\n", "command_rate_hz: nan is not a finite number"),
        (
            MINIMAL + "    abh3_id: one\n",
            "units[0].abh3_id: expected an integer 0–253, got a string 'one'",
        ),
        (MINIMAL + "    protocol: 2022\n", "units[0].protocol: 2022 is not one of: 2021, 2023"),
        (
            MINIMAL + "    bus: can1\n",
            "units[0].bus: 'can1' is not a declared bus (declared: can0)",
        ),
        (
            MINIMAL + "    startup: ['SERVO ON']\n",
            "robot.yaml:5: units[0].startup[0]: 'SERVO ON': SERVO takes two values",
        ),
        (MINIMAL + "  - name: drive\n", "robot.yaml:5: units[1].name: duplicate unit name 'drive'"),
        (
            MINIMAL + "  - name: other\n",
            "units[1].abh3_id: unit 'drive' already uses abh3_id 1 on bus 'can0'",
        ),
        (
            MINIMAL + "    host_id: 1\n",
            "units[0].host_id: host_id 1 is the abh3_id of unit 'drive'",
        ),
        (
            "buses:\n  can0: {bitrate: 125000}\nunits: [{name: a}]\n",
            "robot.yaml:2: buses.can0.bitrate: 125000 is not an ABH3 bitrate",
        ),
        (
            "buses:\n  can0: {}\n  can0: {}\nunits: [{name: a}]\n",
            "robot.yaml:3: buses.can0: duplicate key",
        ),
        (
            "buses:\n  a: {}\n  b: {}\nunits: [{name: x}]\n",
            "units[0].bus: missing: several buses are declared",
        ),
        ("buses:\n  can0: {}\nunits: [{abh3_id: 3}]\n", "units[0].name: missing"),
        ("buses:\n  can0: {}\nunits: [{name: 'my unit'}]\n", "'my unit': unit names are letters"),
        ("buses:\n  can0: {}\nunits: [{name: a}]\nextra: 1\n", "robot.yaml:4: extra: unknown key"),
        (
            "buses:\n  can0: {simulate: {acel: 3}}\nunits: [{name: a}]\n",
            "buses.can0.simulate.acel: unknown key; did you mean 'accel'?",
        ),
    ],
)
def test_errors_name_file_line_and_key(text: str, expected: str) -> None:
    found = problems(text)
    assert any(expected in p for p in found), found


def test_all_problems_are_reported_at_once() -> None:
    found = problems(MINIMAL + "    abh3_id: 999\n    priority: 9\n")
    assert len(found) == 2


def test_cli_reports_config_errors_with_exit_2_and_no_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(MINIMAL + "    priority: 9\n")
    assert main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"error: {bad}:5: units[0].priority: 9 is out of range (allowed 0–7)" in err
    assert "Traceback" not in err


def test_cli_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(tmp_path / "nope.yaml"), "--headless"]) == 2
    assert "cannot read configuration" in capsys.readouterr().err
