"""The seed's input-service command language, parsed strictly, placed per generation."""

from __future__ import annotations

import pytest

from abh3_supervisor.config import parse_config
from abh3_supervisor.core.commands import (
    KEYWORDS,
    CurrentCommand,
    InputChange,
    SelectCommand,
    SwitchCommand,
    VelocityCommand,
    input_change,
    parse_command,
)
from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol.flags import LAYOUT_2021, LAYOUT_2023
from tests.support.rig import TWO_UNITS, Rig

# text, 2021 (data, mask) — the seed's layout, protocol doc §5 — and 2023 (data, mask)
CASES = [
    ("SERVO ON ON", (0x1001, 0x1001), (0x0101, 0x0101)),
    ("SERVO 1 0", (0x0001, 0x1001), (0x0001, 0x0101)),
    ("servo off on", (0x1000, 0x1001), (0x0100, 0x0101)),
    ("START ON OFF", (0x0002, 0x2002), (0x0002, 0x0202)),
    ("START ON ON", (0x2002, 0x2002), (0x0202, 0x0202)),
    ("DIR 1 1", (0x4004, 0x4004), (0x0404, 0x0404)),
    ("CADD ON ON", (0x8008, 0x8008), (0x0808, 0x0808)),
    ("CDIR ON ON", (0x00800080, 0x00800080), (0x8080, 0x8080)),
    ("PCLR ON ON", (0x00080100, 0x00080100), (0x00300000, 0x00300000)),
    ("PCLR ON OFF", (0x00000100, 0x00080100), (0x00100000, 0x00300000)),
    ("TORQUE ON ON", (0x03000000, 0x03000000), (0x00030000, 0x00030000)),
    ("M/S ON ON", (1 << 26, 1 << 26), (1 << 18, 1 << 18)),
    ("BRAKE 1 1", (1 << 28, 1 << 28), (1 << 19, 1 << 19)),
    ("BRAKE ON ON", (1 << 28, 1 << 28), (0x00080000, 0x00080000)),
    ("RESET ON ON", (1 << 31, 1 << 31), (0x00400000, 0x00400000)),  # the maker's v2.0 word
    ("RESET OFF 0", (0, 1 << 31), (0, 1 << 22)),
    ("SELECT 7 7", (0x00070070, 0x00070070), (0x7070, 0x7070)),
    ("SELECT 0 5", (0x00050000, 0x00070070), (0x5000, 0x7070)),
    ("  SELECT   3\t1 ", (0x00010030, 0x00070070), (0x1030, 0x7070)),
]


@pytest.mark.parametrize(("text", "old", "new"), CASES)
def test_every_command_sets_exactly_the_documented_bits(
    text: str, old: tuple[int, int], new: tuple[int, int]
) -> None:
    command = parse_command(text)
    assert isinstance(command, SwitchCommand | SelectCommand)
    assert input_change(command, LAYOUT_2021) == InputChange(*old)
    assert input_change(command, LAYOUT_2023) == InputChange(*new)


def test_the_makers_example_words() -> None:
    def word(layout: object, *texts: str) -> int:
        data = 0
        for text in texts:
            command = parse_command(text)
            assert isinstance(command, SwitchCommand | SelectCommand)
            change = input_change(command, layout)  # type: ignore[arg-type]
            data = data & ~change.mask | change.data
        return data

    # the maker's Linux sample v2.0: servo + start + select 7 on both axes; error reset
    assert word(LAYOUT_2023, "SERVO ON ON", "START ON ON", "SELECT 7 7") == 0x00007373
    assert word(LAYOUT_2023, "RESET ON ON") == 0x00400000
    # its Arduino sample's servo + start mask
    assert (
        input_change(SwitchCommand("SERVO", True, True), LAYOUT_2023).mask
        | input_change(SwitchCommand("START", True, True), LAYOUT_2023).mask
        == 0x00000303
    )
    assert word(LAYOUT_2021, "SERVO ON ON", "START ON ON", "SELECT 7 7") == 0x00073073


def test_velocity_and_current_extensions() -> None:
    assert parse_command("VEL 100 -20.5") == VelocityCommand(100.0, -20.5)
    assert parse_command("cur 5 5") == CurrentCommand(5.0, 5.0)
    assert parse_command("VEL -6553.6 1e3") == VelocityCommand(-6553.6, 1000.0)
    assert parse_command("VEL .5 +2.") == VelocityCommand(0.5, 2.0)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("", "empty"),
        ("   ", "empty"),
        ("FOO", "unknown command 'FOO'"),
        ("SERVO", "takes two values"),
        ("SERVO ON", "takes two values"),
        ("SERVO ON ON ON", "takes two values"),
        ("SERVO_ON_ON", "unknown command"),
        ("SERVO YES ON", "'YES' is not ON, OFF, 1 or 0"),
        ("SERVOX ON ON", "unknown command"),
        ("BRAKE ON OFF", "one bit for both axes"),
        ("RESET 1 0", "one bit for both axes"),
        ("SELECT 8 0", "not a data select value"),
        ("SELECT -1 0", "not a data select value"),
        ("SELECT 07 0", "not a data select value"),
        ("VEL nan 0", "not a number"),
        ("VEL inf 0", "not a number"),
        ("VEL 1e999 0", "not a finite number"),
        ("VEL x 0", "not a number"),
        ("VEL 1_000 0", "not a number"),
        ("SELECT ² 7", "printable ASCII"),  # '²'.isdigit() is True
        ("VEL ١٠ 0", "printable ASCII"),  # float() reads Arabic-Indic digits
        ("SERVO\u3000ON ON", "printable ASCII"),  # str.split() splits on it
        ("SERVO ON ON\x00", "printable ASCII"),
        ("S" * 201, "longer than"),
    ],
)
def test_strict_parsing(text: str, why: str) -> None:
    with pytest.raises(CommandError, match=why):
        parse_command(text)


def test_one_bit_commands_keep_one_value() -> None:
    assert parse_command("brake on 1") == SwitchCommand("BRAKE", True, True)


# one valid command per keyword, in capitals as the seed documents it
EVERY_KEYWORD = {
    **{k: f"{k} ON OFF" for k in ("SERVO", "START", "DIR", "CADD", "CDIR", "PCLR", "TORQUE")},
    **{k: f"{k} ON ON" for k in ("M/S", "BRAKE", "RESET")},
    "SELECT": "SELECT 3 5",
    "VEL": "VEL 50 -1E1",
    "CUR": "CUR 12.5 0",
}


@pytest.mark.parametrize("text", EVERY_KEYWORD.values())
def test_every_keyword_and_switch_value_in_any_case(text: str) -> None:
    """Case-insensitive: what a person types (`vel 50 0`, `Servo on on`) is the command
    the capitals are; only numbers and 0/1 have no case (an exponent takes either)."""
    assert set(EVERY_KEYWORD) == set(KEYWORDS)
    want = parse_command(text)
    for typed in (text.lower(), text.title(), text.swapcase()):
        assert parse_command(typed) == want, typed


def test_the_seeds_answers_do_not_depend_on_case() -> None:
    """The same answers and the same state from the Supervisor (where the TUI's command
    line, `abh3 send` and the ROS 2 service end) for the capitals and the typed forms."""
    cfg = parse_config(TWO_UNITS, "two.yaml")
    typed = ["Servo on on", "start ON on", "vel 50 0", "select 7 7", "servo maybe on", "vel"]
    capitals = [t.upper() for t in typed]
    results = []
    for texts in (capitals, typed):
        rig = Rig(cfg)
        rig.run(0.2)
        answers = [rig.sup.apply_text("left", t) for t in texts]
        unit = rig.sup.units["left"]
        results.append((answers, unit.inputs, unit.setpoint.ay, unit.setpoint.bx))
    assert results[0] == results[1]
    assert results[1][0] == ["", "", "", "", "Invalid Command.", "Invalid Command."]
    assert results[1][2:] == (50, 0)
