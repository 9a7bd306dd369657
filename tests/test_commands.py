"""The seed's input-service command language, parsed strictly."""

from __future__ import annotations

import pytest

from abh3_supervisor.commands import (
    CurrentCommand,
    InputChange,
    VelocityCommand,
    parse_command,
)
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags


@pytest.mark.parametrize(
    ("text", "data", "mask"),
    [
        ("SERVO ON ON", 0x1001, 0x1001),
        ("SERVO 1 0", 0x0001, 0x1001),
        ("servo off on", 0x1000, 0x1001),
        ("START ON OFF", 0x0002, 0x2002),
        ("DIR 1 1", 0x4004, 0x4004),
        ("CADD ON ON", 0x8008, 0x8008),
        ("CDIR ON ON", 0x00800080, 0x00800080),
        ("PCLR ON ON", 0x00080100, 0x00080100),
        ("TORQUE ON ON", 0x03000000, 0x03000000),
        ("M/S ON ON", 1 << 26, 1 << 26),
        ("BRAKE 1 1", 1 << 28, 1 << 28),
        ("RESET ON ON", 1 << 31, 1 << 31),
        ("RESET OFF 0", 0, 1 << 31),
        ("SELECT 7 7", 0x00070070, 0x00070070),
        ("SELECT 0 5", 0x00050000, 0x00070070),
        ("  SELECT   3\t1 ", 0x00010030, 0x00070070),
    ],
)
def test_input_commands(text: str, data: int, mask: int) -> None:
    assert parse_command(text) == InputChange(data, mask)


def test_velocity_and_current_extensions() -> None:
    assert parse_command("VEL 100 -20.5") == VelocityCommand(100.0, -20.5)
    assert parse_command("cur 5 5") == CurrentCommand(5.0, 5.0)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("", "empty"),
        ("FOO", "unknown command 'FOO'"),
        ("SERVO", "takes two values"),
        ("SERVO ON", "takes two values"),
        ("SERVO ON ON ON", "takes two values"),
        ("SERVO_ON_ON", "unknown command"),
        ("SERVO YES ON", "'YES' is not ON, OFF, 1 or 0"),
        ("SERVOX ON ON", "unknown command"),
        ("BRAKE ON OFF", "one bit for both axes"),
        ("SELECT 8 0", "not a data select value"),
        ("SELECT -1 0", "not a data select value"),
        ("VEL nan 0", "not a finite number"),
        ("VEL inf 0", "not a finite number"),
        ("VEL x 0", "not a number"),
    ],
)
def test_strict_parsing(text: str, why: str) -> None:
    with pytest.raises(CommandError, match=why):
        parse_command(text)


def test_bits_match_the_flag_table() -> None:
    change = parse_command("SERVO ON ON")
    assert isinstance(change, InputChange)
    assert change.data == flags.SERVO_BITS
