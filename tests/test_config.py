"""YAML configuration: defaults, and every error naming file, line and key."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import ControlMode, Role, VelocityModel, load_config, parse_config
from abh3_supervisor.config.source import MAX_BYTES, MAX_VALUES
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
    startup: []  # a monitor unit takes no commands
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
            "command_rate_hz: 0 is out of range (allowed 1–1000)",
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


@pytest.mark.wallclock
def test_cli_reports_config_errors_with_exit_2_and_no_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(MINIMAL + "    priority: 9\n")
    assert main(["check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"error: {bad}:5: units[0].priority: 9 is out of range (allowed 0–7)" in err
    assert "Traceback" not in err


@pytest.mark.wallclock
def test_cli_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(tmp_path / "nope.yaml"), "--headless"]) == 2
    assert "cannot read configuration" in capsys.readouterr().err


# ---------------------------------------------------------------- loader limits


def read_problems(path: Path) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config(path)
    return info.value.problems


def test_a_file_above_the_size_limit_is_refused_without_reading_it_all(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_bytes(MINIMAL.encode() + b"#" * MAX_BYTES)
    assert read_problems(big) == [
        f"{big}:1: file: larger than 512 KiB, not a configuration (is this the right file?)"
    ]


def test_text_must_be_utf8_and_the_bad_byte_is_located(tmp_path: Path) -> None:
    latin1 = tmp_path / "latin1.yaml"
    latin1.write_bytes(MINIMAL.replace("drive", "gr\xfcn").encode("latin-1"))
    assert read_problems(latin1) == [
        f"{latin1}:4: encoding: byte 0xFC in column 13 is not UTF-8 (save the file as UTF-8)"
    ]
    bom = tmp_path / "bom.yaml"
    bom.write_bytes(b"\xef\xbb\xbf" + MINIMAL.encode())
    assert list(load_config(bom).units) == ["drive"]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            MINIMAL + "    host_id: \x00\n",
            "robot.yaml:5: invalid YAML: character 0x00 is not allowed",
        ),
        ("x: " + "{a: " * 40 + "1" + "}" * 40 + "\n" + MINIMAL, "robot.yaml:1: nesting: more than"),
        ("x: &x [*x]\n" + MINIMAL, "robot.yaml:1: x[0]: this alias refers to the value it is"),
        (
            MINIMAL + "    name: !!binary aGVsbG8=\n",
            "robot.yaml:5: units[0].name: the tag !!binary",
        ),
        (
            MINIMAL + "    x: !!set {a, b}\n",
            "robot.yaml:5: units[0].x: the tag !!set is not allowed",
        ),
        (MINIMAL + "    ? !!python/name:os.system\n    : 1\n", "the tag !!python/name:os.system"),
        (MINIMAL + "    abh3_id: !custom 3\n", "units[0].abh3_id: the tag !custom is not allowed"),
        (
            "d: &d {host_id: 3}\n" + MINIMAL + "    <<: *d\n",
            "robot.yaml:6: units[0].<<: merge keys",
        ),
        (MINIMAL + "    ? {a: 1}\n    : x\n", "robot.yaml:5: units[0]: a key must be a plain name"),
        (MINIMAL + "    ? [a]\n    : x\n", "units[0]: a key must be a plain name, not a list"),
        (MINIMAL + "    abh3_id: 2001-13-45\n", "robot.yaml:5: units[0].abh3_id: cannot read"),
        ("- a\n- b\n", "robot.yaml:1: (top level): expected a mapping with buses, units"),
        ("hello\n", "robot.yaml:1: (top level): expected a mapping"),
    ],
)
def test_hostile_yaml_gets_a_located_message(text: str, expected: str) -> None:
    found = problems(text)
    assert any(expected in p for p in found), found


def test_alias_expansion_is_bounded_and_fast() -> None:
    rows = ["a0: &a0 [" + ", ".join(["lol"] * 9) + "]"]
    rows += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 10)]
    started = time.monotonic()
    found = problems("\n".join(rows) + "\n" + MINIMAL)
    assert time.monotonic() - started < 1.0
    assert (
        len(found) == 1 and f"more than {MAX_VALUES} values once aliases are expanded" in found[0]
    )
    assert found[0].startswith("robot.yaml:1: a")


def test_aliases_within_the_limit_are_fine() -> None:
    cfg = parse_config(
        "buses:\n  can0: {}\nunits:\n"
        "  - {name: a, abh3_id: 1, startup: &s ['SERVO ON ON']}\n"
        "  - {name: b, abh3_id: 3, startup: *s}\n",
        "alias.yaml",
    )
    assert cfg.units["b"].startup == ("SERVO ON ON",)


# ---------------------------------------------------------------- values


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (
            "buses:\n  can0:\n    simulate:\nunits: [{name: a}]\n",
            "robot.yaml:3: buses.can0.simulate: expected true, false or a mapping of simulator "
            "options, got None",
        ),
        (
            "buses:\n  can0: {channel: [a, b]}\nunits: [{name: a}]\n",
            "buses.can0.channel: expected one channel name or number, got ['a', 'b']",
        ),
        (
            "buses:\n  can0: {options: 5}\nunits: [{name: a}]\n",
            "buses.can0.options: expected a mapping, got int",
        ),
        (
            "buses:\n  can0: {options: {channel: can1}}\nunits: [{name: a}]\n",
            "buses.can0.options.channel: set channel on the bus itself, not in its options",
        ),
        ("buses:\n  can0: {}\nunits: [{name: 12}]\n", "units[0].name: expected a non-empty string"),
        ("buses: [can0]\nunits: [{name: a}]\n", "robot.yaml:1: buses: expected a mapping"),
        ("buses:\n  can0: {}\nunits: [{name: a}]\nplugins: 5\n", "plugins: expected a mapping"),
        (MINIMAL + "    command_rate_hz: 1e-300\n", "YAML reads 1e-300 as text: write it with a"),
        (MINIMAL + "    command_rate_hz: 1.0e-300\n", "1e-300 is out of range (allowed 1–1000)"),
        (MINIMAL + "    broadcast: {rate_hz: 0.001}\n", "rate_hz: 0.001 is out of range"),
        (MINIMAL + "    geometry: {wheel: 1.0e-300}\n", "geometry.wheel: 1e-300 is out of range"),
        (MINIMAL + "    drive_timeout_ms: 0\n", "drive_timeout_ms: 0 is out of range (allowed 10–"),
        (MINIMAL + "    command_rate_hz: 2001-12-14\n", "got a date '2001-12-14'"),
    ],
)
def test_values_of_the_wrong_kind(text: str, expected: str) -> None:
    found = problems(text)
    assert any(expected in p for p in found), found


def test_one_mistake_gives_one_message() -> None:
    assert problems("buses:\n  can0: {}\nunits: [{name: 12}]\n") == [
        "robot.yaml:3: units[0].name: expected a non-empty string, got 12"
    ]
    assert problems("units: [{name: a}]\n") == [
        "robot.yaml:1: buses: missing: declare at least one bus"
    ]


def test_an_empty_unit_list_is_told_to_declare_one() -> None:
    assert problems("buses:\n  can0: {}\nunits: []\n") == [
        "robot.yaml:3: units: declare at least one unit (each a mapping with at least 'name')"
    ]
    assert problems("buses:\n  can0: {}\nunits: {a: 1}\n") == [
        "robot.yaml:3: units: expected a list of units (each a mapping with at least 'name')"
    ]


# ---------------------------------------------------------------- timing rules


def test_drive_timeout_defaults_to_the_seeds_drive_setting() -> None:
    assert parse_config(MINIMAL, "m.yaml").units["drive"].drive_timeout_ms == 500
    cfg = parse_config(MINIMAL + "    drive_timeout_ms: 750\n    command_rate_hz: 5\n", "m.yaml")
    assert cfg.units["drive"].drive_timeout_ms == 750


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        (
            "command_rate_hz: 4",
            "robot.yaml:5: units[0].command_rate_hz: 4 Hz sends a command every 250 ms: not under "
            "half of drive_timeout_ms 500 (the drive stops itself after that long without one); "
            "use more than 4 Hz",
        ),
        (
            "reply_timeout_ms: 60000",
            "robot.yaml:5: units[0].reply_timeout_ms: 60000 ms is not below drive_timeout_ms 500",
        ),
        (
            "drive_timeout_ms: 100",
            "robot.yaml:5: units[0].reply_timeout_ms: 100 ms is not below drive_timeout_ms 100",
        ),
        (
            "timeout_ms: 150",
            "robot.yaml:5: units[0].timeout_ms: 150 ms would take the unit offline after one lost "
            "reply: use at least 200 ms (twice the longer of the command period 20 ms and "
            "reply_timeout_ms 100)",
        ),
        (
            "timeout_ms: 5001",
            "robot.yaml:5: units[0].timeout_ms: 5001 ms is more than 10 × drive_timeout_ms 500",
        ),
    ],
)
def test_timing_rules_keep_the_drive_alive(keys: str, expected: str) -> None:
    found = problems(MINIMAL + f"    {keys}\n")
    assert any(p.startswith(expected) for p in found), found


def test_a_monitor_does_not_feed_the_drive_timeout_but_offline_still_means_silent() -> None:
    monitor = MINIMAL + "    role: monitor\n    command_rate_hz: 2\n"
    assert parse_config(monitor + "    timeout_ms: 20000\n", "m.yaml").units["drive"]
    assert "at least 1000 ms" in problems(monitor + "    timeout_ms: 999\n")[0]


def test_timing_rules_wait_for_sound_values() -> None:
    # a broken rate is reported once, not again as a broken period
    assert len(problems(MINIMAL + "    command_rate_hz: fast\n")) == 1


@pytest.mark.parametrize(
    ("unit", "why"),
    [
        ("control: current, startup: ['VEL 100 100']", "needs TORQUE OFF OFF first"),
        ("role: monitor, startup: ['SERVO ON ON']", "role: monitor and takes no commands"),
        ("startup: ['TORQUE ON ON', 'VEL 1 1']", r"startup\[1\]: would be refused at start"),
    ],
)
def test_startup_commands_that_would_be_refused_are_config_errors(unit: str, why: str) -> None:
    text = f"buses: {{b: {{interface: virtual, channel: x}}}}\nunits:\n  - {{name: u, {unit}}}\n"
    with pytest.raises(ConfigError, match=why) as info:
        parse_config(text, "s.yaml")
    assert info.value.problems[0].startswith("s.yaml:3: units[0].startup")


@pytest.mark.wallclock
def test_the_teleop_example_writes_its_csv_under_a_git_ignored_logs_folder_it_creates(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`abh3 run configs/teleop.yaml` from a checkout leaves nothing for git to show: its
    recording goes to logs/ (ignored), which the csv plugin creates when it is missing."""
    root = Path(__file__).resolve().parent.parent
    teleop = root / "configs" / "teleop.yaml"
    assert load_config(teleop).plugins["csv"]["path"] == "logs/teleop.csv"
    assert "logs/" in (root / ".gitignore").read_text().splitlines()
    monkeypatch.chdir(tmp_path)  # a checkout without logs/ yet
    args = ["run", str(teleop), "--headless", "--duration", "0.3", "--status-interval", "0"]
    assert main(args) == 0, capsys.readouterr().err
    rows = (tmp_path / "logs" / "teleop.csv").read_text().splitlines()
    assert rows[0].startswith("time [s],note,unit,") and len(rows) > 2
