"""The simulated drive's parameter table follows the file, and ``simulate.params`` sets a
drive up otherwise (issue 22 item 6): what it reports is what it does."""

from __future__ import annotations

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.params import table
from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.simulator import SimBus
from tests.support.rig import Rig

UNITS = """
buses:
  b: {{interface: virtual, channel: t, bitrate: 250000, simulate: {simulate}}}
units:
  - {{name: left, abh3_id: 4, host_id: 7, brd_group: 9, drive_timeout_ms: 400}}
  - {{name: right, abh3_id: 3, protocol: "2023"}}
"""


def values(rig: Rig, unit: str, *addresses: int) -> list[float]:
    params = rig.drive(unit).tel.params
    return [table.to_value(params[a], table.kind_of(a)) for a in addresses]


def rig_of(simulate: str) -> Rig:
    config = parse_config(UNITS.format(simulate=simulate), "s.yaml")
    rig = Rig(config)
    sim = config.buses["b"].simulate
    assert sim is not None
    # as the runtime builds it: with the bus's bitrate (the Rig leaves it out)
    rig.sim.drives.update(SimBus.for_units(config.units_on("b"), sim, 0.0, bitrate=250_000).drives)
    return rig


def test_the_table_is_the_drive_the_file_describes() -> None:
    rig = rig_of("{error_timeout_ms: 1500, dp0_period_ms: 20}")
    # bitrate (kbit/s), address, host, reply mode, group, command-zero and error timeouts
    got = values(rig, "left", 0x4101, 0x4102, 0x4103, 0x4105, 0x4107, 0x4117, 0x4118)
    assert got == [250, 4, 7, 20, 9, 400, 1500]
    assert values(rig, "right", 0x4103, 0x4117) == [2, 500]
    assert rig.drive("left").command_zero_ms == 400


def test_params_override_the_file_and_the_drive_acts_on_its_timeouts() -> None:
    rig = rig_of("{params: {left: {0x4117: 750, CAN_HOST_ADDRESS: 5, 0x4118: 3000}}}")
    assert values(rig, "left", 0x4117, 0x4103, 0x4118) == [750, 5, 3000]
    drive = rig.drive("left")
    assert (drive.command_zero_ms, drive.error_timeout_ms) == (750, 3000)
    assert values(rig, "right", 0x4117, 0x4103) == [500, 2]  # the other drive: as the file


def test_a_drive_with_a_longer_command_zero_timeout_stops_later() -> None:
    config = parse_config(UNITS.format(simulate="{params: {left: {0x4117: 750}}}"))
    sim = config.buses["b"].simulate
    assert sim is not None
    drive = SimBus.for_units(config.units_on("b"), sim, 0.0).drives[4]
    drive.on_frame(ids.dp0_command_id(4, 7), frames.encode_dp0_command(0, 0, 0), 0.1)
    drive.advance(0.1 + 0.6)  # the file's 400 ms have passed, the drive's 750 not
    assert not drive.alarm_word() & flags.CAN_COMM_ERROR
    drive.advance(0.1 + 0.75)
    assert drive.alarm_word() & flags.CAN_COMM_ERROR


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ("{middle: {0x4117: 750}}", "params.middle: no unit 'middle' on bus b"),
        ("{left: {CAN_NOTHING: 1}}", "'CAN_NOTHING' is no parameter name or address"),
        ("{left: {0x12345: 1}}", "address 0x12345 is not 0x0000-0xFFFF"),
        ("{left: {0x4117: .nan}}", "0x4117 CAN_COMMAND_ZERO_TIMEOUT: nan is not a finite number"),
        ("{left: {0x4117: fast}}", "expected a number (the value, e.g. 750), got 'fast'"),
        ("{left: {0x4117: true}}", "expected a number"),
        ("{left: {0x4117: 1.0e+80}}", "beyond the packed-float range"),
        ("{left: {0x4117: 1.0e3}}", "YAML reads 1.0e3 as text: write it with a dot and a signed"),
        ("{left: {0x411A: 1.5}}", "0x411A CAN_CONTROL_FLAG_LOGIC: 1.5 is not a 32-bit integer"),
        ("{left: 750}", "params.left: expected a mapping of address → value"),
    ],
)
def test_params_mistakes_are_file_line_errors(params: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(UNITS.format(simulate=f"{{params: {params}}}"), "s.yaml")
    assert any(p.startswith("s.yaml:3: ") and message in p for p in info.value.problems), (
        info.value.problems
    )
