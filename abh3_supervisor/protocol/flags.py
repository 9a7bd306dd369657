"""Flag words (protocol doc §5) with every bit named in English and Japanese.

The input word (host → drive) and the control word (drive state) share bit positions; so
do the error and alarm words. Japanese labels follow the vendor ROS 2 manual.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class FlagBit:
    bit: int
    name: str
    en: str
    ja: str

    @property
    def mask(self) -> int:
        return 1 << self.bit


class FlagWord:
    """A 32-bit word whose bits have names; unnamed bits are reported as ``bitN``."""

    def __init__(self, name: str, bits: tuple[FlagBit, ...]) -> None:
        self.name = name
        self.bits = bits
        self._by_name = {b.name: b for b in bits}
        self._by_bit = {b.bit: b for b in bits}

    def mask(self, name: str) -> int:
        return self._by_name[name].mask

    def set_bits(self, value: int) -> Iterator[FlagBit]:
        """Every set bit of ``value``, named where the word defines a name."""
        for bit in range(32):
            if value >> bit & 1:
                yield self._by_bit.get(bit) or FlagBit(
                    bit, f"bit{bit}", f"bit {bit}", f"ビット{bit}"
                )

    def names(self, value: int) -> list[str]:
        return [b.name for b in self.set_bits(value)]

    def labels(self, value: int, lang: str = "en") -> list[str]:
        return [b.ja if lang == "ja" else b.en for b in self.set_bits(value)]


def _word(name: str, rows: list[tuple[int, str, str, str]]) -> FlagWord:
    return FlagWord(name, tuple(FlagBit(*row) for row in rows))


_INPUT_ROWS = [
    (0, "AY_SERVO_ON", "A/Y servo on", "A/Y サーボ ON"),
    (1, "AY_START", "A/Y start", "A/Y スタート"),
    (2, "AY_CMD_POLARITY", "A/Y command polarity (invert)", "A/Y 指令極性"),
    (3, "AY_CORR_ADD", "A/Y correction add", "A/Y 補正加算"),
    (4, "AY_SELECT0", "A/Y data select 0", "A/Y データ選択 0"),
    (5, "AY_SELECT1", "A/Y data select 1", "A/Y データ選択 1"),
    (6, "AY_SELECT2", "A/Y data select 2", "A/Y データ選択 2"),
    (7, "AY_CORR_POLARITY", "A/Y correction polarity (subtract)", "A/Y 補正極性"),
    (8, "A_PULSE_CLEAR", "A pulse count clear", "A 軸積算クリア"),
    (12, "BX_SERVO_ON", "B/X servo on", "B/X サーボ ON"),
    (13, "BX_START", "B/X start", "B/X スタート"),
    (14, "BX_CMD_POLARITY", "B/X command polarity (invert)", "B/X 指令極性"),
    (15, "BX_CORR_ADD", "B/X correction add", "B/X 補正加算"),
    (16, "BX_SELECT0", "B/X data select 0", "B/X データ選択 0"),
    (17, "BX_SELECT1", "B/X data select 1", "B/X データ選択 1"),
    (18, "BX_SELECT2", "B/X data select 2", "B/X データ選択 2"),
    (19, "B_PULSE_CLEAR", "B pulse count clear", "B 軸積算クリア"),
    (23, "BX_CORR_POLARITY", "B/X correction polarity (subtract)", "B/X 補正極性"),
    (24, "AY_TORQUE", "A/Y torque control (0 = speed)", "A/Y 速度/トルク"),
    (25, "BX_TORQUE", "B/X torque control (0 = speed)", "B/X 速度/トルク"),
    (26, "SLAVE", "slave operation (0 = master)", "マスタ/スレーブ"),
    (28, "BRAKE_RELEASE", "brake released", "ブレーキ"),
    (31, "ERROR_RESET", "error reset", "エラーリセット"),
]
INPUT = _word("input", _INPUT_ROWS)
CONTROL = _word(
    "control",
    [*_INPUT_ROWS, (27, "TRAVEL_MODEL", "travel/turn model (0 = motor axes)", "走行軸モデル")],
)
FAULT = _word(
    "error/alarm",
    [
        (0, "A_MECH_LOCK", "A mechanical lock", "A 軸 メカロック"),
        (1, "B_MECH_LOCK", "B mechanical lock", "B 軸 メカロック"),
        (2, "DRIVER_OVERHEAT", "driver overheat", "ドライバ過熱"),
        (3, "BRAKE_FAULT", "brake fault", "ブレーキ異常"),
        (4, "A_RESOLVER", "A resolver", "A 軸 レゾルバ"),
        (5, "B_RESOLVER", "B resolver", "B 軸 レゾルバ"),
        (6, "A_OVERCURRENT", "A overcurrent", "A 軸 過電流"),
        (7, "B_OVERCURRENT", "B overcurrent", "B 軸 過電流"),
        (8, "CONTROL_UNDERVOLTAGE", "control supply undervoltage", "制御電源 電圧低下"),
        (9, "PARAMETER", "parameter", "パラメータ"),
        (10, "A_PDU", "A PDU", "A 軸 PDU"),
        (11, "B_PDU", "B PDU", "B 軸 PDU"),
        (12, "A_THERMAL", "A electronic thermal", "A 軸 電子サーマル"),
        (13, "B_THERMAL", "B electronic thermal", "B 軸 電子サーマル"),
        (14, "MAIN_UNDERVOLTAGE", "main supply undervoltage", "主電源 電圧低下"),
        (15, "OVERVOLTAGE", "control or main supply overvoltage", "制御電源 過電圧 主電源 過電圧"),
        (16, "A_OVERSPEED", "A overspeed", "A 軸 過速度"),
        (17, "B_OVERSPEED", "B overspeed", "B 軸 過速度"),
        (18, "A_SPEED_LIMIT", "A speed limit", "A 軸 速度リミット"),
        (19, "B_SPEED_LIMIT", "B speed limit", "B 軸 速度リミット"),
        (20, "A_CURRENT_LIMIT", "A current limit", "A 軸 電流リミット"),
        (21, "B_CURRENT_LIMIT", "B current limit", "B 軸 電流リミット"),
        (22, "CAN_COMM_ERROR", "CAN communication error", "CAN 通信異常"),
        (23, "CAN_TRAFFIC_EXCESSIVE", "CAN traffic excessive", "CAN 通信 トラフィック過大"),
    ],
)
_IO_ROWS = [
    (0, "ERROR", "error present", "エラー発生"),
    (1, "ALARM", "alarm present", "アラーム発生"),
    (2, "AY_READY", "A/Y ready (servo on)", "A/Y 軸 レディ"),
    (3, "AY_BUSY", "A/Y busy", "A/Y 軸 ビジー"),
    (4, "BX_READY", "B/X ready (servo on)", "B/X 軸 レディ"),
    (5, "BX_BUSY", "B/X busy", "B/X 軸 ビジー"),
    (6, "ERROR_CODE0", "error code 0", "エラーコード 0"),
    (7, "ERROR_CODE1", "error code 1", "エラーコード 1"),
    (8, "ERROR_CODE2", "error code 2", "エラーコード 2"),
    (9, "ERROR_CODE3", "error code 3", "エラーコード 3"),
    (10, "BRAKE_RELEASED", "brake released", "ブレーキ解放"),
    *[
        (
            11 + i,
            f"DIN{i}",
            f"digital input #{i} (pin {28 + i})",
            f"{28 + i}pin : デジタル入力 #{i}",
        )
        for i in range(4)
    ],
    (15, "DIN12", "digital input #12 (pin 42)", "42pin : デジタル入力 #12"),
    *[
        (
            16 + i,
            f"DIN{13 + i}",
            f"digital input #{13 + i} (pin {43 + i})",
            f"{43 + i}pin : デジタル入力 #{13 + i}",
        )
        for i in range(7)
    ],
    *[
        (
            23 + i,
            f"DIN{4 + i}",
            f"digital input #{4 + i} (pin {32 + i})",
            f"{32 + i}pin : デジタル入力 #{4 + i}",
        )
        for i in range(6)
    ],
    (29, "DIN10", "digital input #10 (pin 40)", "40pin : デジタル入力 #10"),
    (30, "DIN11", "digital input #11 (pin 41)", "41pin : デジタル入力 #11"),
    (31, "ERROR_RESET_INPUT", "error reset input (pin 20)", "20pin : エラーリセット入力"),
]
IO = _word("I/O", _IO_ROWS)

# Masks the supervisor uses by name.
AY_SERVO_ON = INPUT.mask("AY_SERVO_ON")
BX_SERVO_ON = INPUT.mask("BX_SERVO_ON")
AY_START = INPUT.mask("AY_START")
BX_START = INPUT.mask("BX_START")
AY_TORQUE = INPUT.mask("AY_TORQUE")
BX_TORQUE = INPUT.mask("BX_TORQUE")
ERROR_RESET = INPUT.mask("ERROR_RESET")
A_PULSE_CLEAR_MASK = INPUT.mask("A_PULSE_CLEAR")
B_PULSE_CLEAR_MASK = INPUT.mask("B_PULSE_CLEAR")
TRAVEL_MODEL = CONTROL.mask("TRAVEL_MODEL")
AY_SELECT_SHIFT = 4
BX_SELECT_SHIFT = 16
SERVO_BITS = AY_SERVO_ON | BX_SERVO_ON
START_BITS = AY_START | BX_START
CAN_COMM_ERROR = FAULT.mask("CAN_COMM_ERROR")


def data_select(word: int) -> tuple[int, int]:
    """The written 3-bit data-select values (A/Y, B/X); the drive uses set ``7 - value``."""
    return (word >> AY_SELECT_SHIFT) & 7, (word >> BX_SELECT_SHIFT) & 7
