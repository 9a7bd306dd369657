"""Each generation's flag tables against protocol doc §5, bit by bit, and the words we write."""

from __future__ import annotations

import pytest

from abh3_supervisor.protocol.flags import FAULT, LAYOUT_2021, LAYOUT_2023, Layout, layout
from abh3_supervisor.protocol.generation import Generation

# §5, 2021 input/control table (the seed)
INPUT_2021 = {
    0: "AY_SERVO_ON", 1: "AY_START", 2: "AY_CMD_POLARITY", 3: "AY_CORR_ADD",
    4: "AY_SELECT0", 5: "AY_SELECT1", 6: "AY_SELECT2", 7: "AY_CORR_POLARITY",
    8: "A_PULSE_CLEAR", 12: "BX_SERVO_ON", 13: "BX_START", 14: "BX_CMD_POLARITY",
    15: "BX_CORR_ADD", 16: "BX_SELECT0", 17: "BX_SELECT1", 18: "BX_SELECT2",
    19: "B_PULSE_CLEAR", 23: "BX_CORR_POLARITY", 24: "AY_TORQUE", 25: "BX_TORQUE",
    26: "MASTER_SLAVE", 28: "BRAKE_RELEASE", 31: "ERROR_RESET",
}  # fmt: skip
# §5, "2023 layout": operation, input (broadcast 1) and control words
INPUT_2023 = {
    0: "AY_SERVO_ON", 1: "AY_START", 2: "AY_CMD_POLARITY", 3: "AY_CORR_ADD",
    4: "AY_SELECT0", 5: "AY_SELECT1", 6: "AY_SELECT2", 7: "AY_CORR_POLARITY",
    8: "BX_SERVO_ON", 9: "BX_START", 10: "BX_CMD_POLARITY", 11: "BX_CORR_ADD",
    12: "BX_SELECT0", 13: "BX_SELECT1", 14: "BX_SELECT2", 15: "BX_CORR_POLARITY",
    16: "AY_TORQUE", 17: "BX_TORQUE", 18: "MASTER_SLAVE", 19: "BRAKE_RELEASE",
    20: "A_PULSE_CLEAR", 21: "B_PULSE_CLEAR", 22: "ERROR_RESET",
}  # fmt: skip
CONTROL_ONLY_2023 = {
    25: "AY_READY", 26: "AY_BUSY", 27: "BX_READY", 28: "BX_BUSY",
    29: "TRAVEL_MODEL", 30: "BRAKE_RELEASE_OUT", 31: "ERROR",
}  # fmt: skip


def table(word: object) -> dict[int, str]:
    return {b.bit: b.name for b in word.bits}  # type: ignore[attr-defined]


def test_2021_tables() -> None:
    assert table(LAYOUT_2021.input) == INPUT_2021
    assert table(LAYOUT_2021.control) == {**INPUT_2021, 27: "TRAVEL_MODEL"}
    assert LAYOUT_2021.brd1_inputs is None
    io = table(LAYOUT_2021.io)
    assert [io[b] for b in (0, 1, 2, 3, 4, 5, 10, 31)] == [
        "ERROR", "ALARM", "AY_READY", "AY_BUSY", "BX_READY", "BX_BUSY",
        "BRAKE_RELEASED", "ERROR_RESET_INPUT",
    ]  # fmt: skip
    # digital inputs: #0–#3 at 11–14, #12 at 15, #13–#19 at 16–22, #4–#9 at 23–28, #10, #11
    din = {int(name[3:]): bit for bit, name in io.items() if name.startswith("DIN")}
    assert din == {
        **{i: 11 + i for i in range(4)}, 12: 15, **{13 + i: 16 + i for i in range(7)},
        **{4 + i: 23 + i for i in range(6)}, 10: 29, 11: 30,
    }  # fmt: skip


def test_2023_tables() -> None:
    assert table(LAYOUT_2023.input) == INPUT_2023
    assert LAYOUT_2023.brd1_inputs is not None
    assert table(LAYOUT_2023.brd1_inputs) == INPUT_2023
    assert table(LAYOUT_2023.control) == {**INPUT_2023, **CONTROL_ONLY_2023}
    io = table(LAYOUT_2023.io)
    assert io == {
        **{i: f"DOUT{i}" for i in range(8)},
        **{8 + i: f"DIN{i}" for i in range(20)},
        31: "ERROR_RESET_INPUT",
    }


def test_error_and_alarm_are_the_same_in_both() -> None:
    assert LAYOUT_2021.words["error"] is LAYOUT_2023.words["alarm"] is FAULT
    assert len(FAULT.bits) == 24 and FAULT.mask("CAN_COMM_ERROR") == 1 << 22


@pytest.mark.parametrize(
    ("lay", "servo", "start", "torque", "brake", "reset", "select", "travel"),
    [
        (LAYOUT_2021, (1, 1 << 12), (2, 1 << 13), (1 << 24, 1 << 25), 1 << 28, 1 << 31,
         (4, 16), 1 << 27),
        (LAYOUT_2023, (1, 1 << 8), (2, 1 << 9), (1 << 16, 1 << 17), 1 << 19, 1 << 22,
         (4, 12), 1 << 29),
    ],
)  # fmt: skip
def test_masks_the_supervisor_acts_on(
    lay: Layout,
    servo: tuple[int, int],
    start: tuple[int, int],
    torque: tuple[int, int],
    brake: int,
    reset: int,
    select: tuple[int, int],
    travel: int,
) -> None:
    assert (lay.servo, lay.start, lay.torque) == (servo, start, torque)
    assert (lay.brake_release, lay.error_reset, lay.select_shift) == (brake, reset, select)
    assert lay.travel_model == travel


def test_the_makers_example_words_2023() -> None:
    assert LAYOUT_2023.input.names(0x00007373) == [
        "AY_SERVO_ON", "AY_START", "AY_SELECT0", "AY_SELECT1", "AY_SELECT2",
        "BX_SERVO_ON", "BX_START", "BX_SELECT0", "BX_SELECT1", "BX_SELECT2",
    ]  # fmt: skip
    assert LAYOUT_2023.input.names(0x00400000) == ["ERROR_RESET"]
    assert LAYOUT_2023.servo.both | LAYOUT_2023.start.both == 0x00000303


@pytest.mark.parametrize("lay", [LAYOUT_2021, LAYOUT_2023])
def test_the_safe_word_keeps_only_data_select(lay: Layout) -> None:
    everything = lay.input.defined
    assert lay.safe(everything) == lay.select(7, 7)
    assert lay.safe(everything & ~lay.select_mask) == 0
    # the idle word: data select as configured, torque only in current control
    assert lay.idle(7, 6, torque=False) == lay.select(7, 6)
    assert lay.idle(7, 7, torque=True) == lay.select(7, 7) | lay.torque.both


def test_undefined_bits_per_generation() -> None:
    assert LAYOUT_2021.undefined(1 << 9 | 1 << 27 | 1) == 1 << 9 | 1 << 27  # 27: control only
    assert LAYOUT_2023.undefined(1 << 23 | 1 << 25 | 1 << 31 | 1) == 1 << 23 | 1 << 25 | 1 << 31
    assert layout(Generation.G2023) is LAYOUT_2023
