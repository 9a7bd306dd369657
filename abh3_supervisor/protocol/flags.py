"""Flag words (protocol doc §5) per generation, with every bit named in English and Japanese.

The 2023 "new CAN specification" moved every bit of the input ("operation"), control and
I/O words, so each generation has one :class:`Layout`: its words (the only place bit
positions are written) and the masks the supervisor acts on, looked up in those words by
name. Bits that mean the same in both generations share a name (``AY_SERVO_ON``, …), so a
script that filters on a name works on either. The error and alarm words are the same in
both generations. Japanese labels of the 2021 words follow the vendor ROS 2 manual; those
of the 2023-only bits are ours, in the same style.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import NamedTuple

from abh3_supervisor.protocol.generation import Generation


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
        self.bits = tuple(sorted(bits, key=lambda b: b.bit))
        self._by_name = {b.name: b for b in bits}
        self._by_bit = {b.bit: b for b in bits}
        if len(self._by_name) != len(bits) or len(self._by_bit) != len(bits):
            raise ValueError(f"{name}: a bit or a name is defined twice")
        self.defined = sum(b.mask for b in bits)  # every bit this word names

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def mask(self, name: str) -> int:
        return self._by_name[name].mask

    def bit(self, name: str) -> int:
        return self._by_name[name].bit

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


Row = tuple[int, str, str, str]


def _word(name: str, rows: list[Row]) -> FlagWord:
    return FlagWord(name, tuple(FlagBit(*row) for row in rows))


def _inputs(first: int, pin: int, number: int, count: int) -> list[Row]:
    """``count`` digital inputs #number… at bits first… on pins pin…"""
    return [
        (
            first + i,
            f"DIN{number + i}",
            f"digital input #{number + i} (pin {pin + i})",
            f"{pin + i}pin : デジタル入力 #{number + i}",
        )
        for i in range(count)
    ]


# ---------------------------------------------------------------- error / alarm (both)

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
CAN_COMM_ERROR = FAULT.mask("CAN_COMM_ERROR")

# ---------------------------------------------------------------- 2021 (the seed)

_INPUT_2021: list[Row] = [
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
    (26, "MASTER_SLAVE", "slave operation (0 = master)", "マスタ/スレーブ"),
    (28, "BRAKE_RELEASE", "brake released", "ブレーキ"),
    (31, "ERROR_RESET", "error reset", "エラーリセット"),
]
_IO_2021: list[Row] = [
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
    *_inputs(11, 28, 0, 4),
    *_inputs(15, 42, 12, 1),
    *_inputs(16, 43, 13, 7),
    *_inputs(23, 32, 4, 6),
    *_inputs(29, 40, 10, 2),
    (31, "ERROR_RESET_INPUT", "error reset input (pin 20)", "20pin : エラーリセット入力"),
]

# ---------------------------------------------------------------- 2023 ("new CAN spec")

_INPUT_2023: list[Row] = [
    (0, "AY_SERVO_ON", "A/Y servo on", "A/Y サーボ ON"),
    (1, "AY_START", "A/Y start", "A/Y スタート"),
    (2, "AY_CMD_POLARITY", "A/Y command reverse", "A/Y 指令反転"),
    (3, "AY_CORR_ADD", "A/Y correction add", "A/Y 補正加算"),
    (4, "AY_SELECT0", "A/Y data select 0", "A/Y データ選択 0"),
    (5, "AY_SELECT1", "A/Y data select 1", "A/Y データ選択 1"),
    (6, "AY_SELECT2", "A/Y data select 2", "A/Y データ選択 2"),
    (7, "AY_CORR_POLARITY", "A/Y correction subtract", "A/Y 補正減算"),
    (8, "BX_SERVO_ON", "B/X servo on", "B/X サーボ ON"),
    (9, "BX_START", "B/X start", "B/X スタート"),
    (10, "BX_CMD_POLARITY", "B/X command reverse", "B/X 指令反転"),
    (11, "BX_CORR_ADD", "B/X correction add", "B/X 補正加算"),
    (12, "BX_SELECT0", "B/X data select 0", "B/X データ選択 0"),
    (13, "BX_SELECT1", "B/X data select 1", "B/X データ選択 1"),
    (14, "BX_SELECT2", "B/X data select 2", "B/X データ選択 2"),
    (15, "BX_CORR_POLARITY", "B/X correction subtract", "B/X 補正減算"),
    (16, "AY_TORQUE", "A/Y torque control (0 = speed)", "A/Y 速度/トルク"),
    (17, "BX_TORQUE", "B/X torque control (0 = speed)", "B/X 速度/トルク"),
    (18, "MASTER_SLAVE", "master/slave enable", "マスタ/スレーブ有効"),
    (19, "BRAKE_RELEASE", "brake release", "ブレーキ解放"),
    (20, "A_PULSE_CLEAR", "A pulse count clear", "A 軸積算クリア"),
    (21, "B_PULSE_CLEAR", "B pulse count clear", "B 軸積算クリア"),
    (22, "ERROR_RESET", "error reset", "エラーリセット"),
]
_CONTROL_ONLY_2023: list[Row] = [
    (25, "AY_READY", "A/Y ready (servo on)", "A/Y 軸 レディ"),
    (26, "AY_BUSY", "A/Y busy (command ≠ 0)", "A/Y 軸 ビジー"),
    (27, "BX_READY", "B/X ready (servo on)", "B/X 軸 レディ"),
    (28, "BX_BUSY", "B/X busy (command ≠ 0)", "B/X 軸 ビジー"),
    (29, "TRAVEL_MODEL", "travel/turn model (0 = motor axes)", "走行軸モデル"),
    (30, "BRAKE_RELEASE_OUT", "brake release output on", "ブレーキ解放出力"),
    (31, "ERROR", "an error is present", "エラー発生"),
]
_IO_2023: list[Row] = [
    *[(i, f"DOUT{i}", f"digital output #{i}", f"デジタル出力 #{i}") for i in range(8)],
    *[(8 + i, f"DIN{i}", f"digital input #{i}", f"デジタル入力 #{i}") for i in range(20)],
    (31, "ERROR_RESET_INPUT", "error reset input", "エラーリセット入力"),
]


class Pair(NamedTuple):
    """One mask per axis (A/Y, B/X)."""

    ay: int
    bx: int

    @property
    def both(self) -> int:
        return self.ay | self.bx

    def of(self, axis: int) -> int:
        return self.bx if axis else self.ay


@dataclass(frozen=True)
class Layout:
    """One generation's flag words and the masks the supervisor acts on.

    ``input`` is what the host writes (DP0 bytes 4–7; "operation" in 2023); ``control`` the
    drive's state (2021: broadcast 1 word 0; 2023: the DP0 reply); ``io`` broadcast 1's I/O
    word; ``brd1_inputs`` broadcast 1's second word in 2023 (None in 2021). Every mask below
    is looked up in these words by name.
    """

    generation: Generation
    input: FlagWord
    control: FlagWord
    io: FlagWord
    brd1_inputs: FlagWord | None
    servo: Pair
    start: Pair
    reverse: Pair
    corr_add: Pair
    corr_subtract: Pair
    pulse_clear: Pair
    torque: Pair
    select_shift: Pair
    master_slave: int
    brake_release: int
    error_reset: int
    travel_model: int  # in the control word
    # status bits of the control word saying what the drive does (2023 only; else 0)
    ready: Pair
    busy: Pair

    @classmethod
    def build(
        cls,
        generation: Generation,
        input_rows: list[Row],
        control_rows: list[Row],
        io_rows: list[Row],
        brd1_inputs: bool,
    ) -> Layout:
        inputs = _word("input", input_rows)
        control = _word("control", [*input_rows, *control_rows])
        m, c = inputs.mask, control.mask

        def pair(name: str, word: FlagWord = inputs) -> Pair:
            return Pair(word.mask(f"AY_{name}"), word.mask(f"BX_{name}"))

        has_status = "AY_READY" in control
        return cls(
            generation=generation,
            input=inputs,
            control=control,
            io=_word("I/O", io_rows),
            brd1_inputs=_word("input", input_rows) if brd1_inputs else None,
            servo=pair("SERVO_ON"),
            start=pair("START"),
            reverse=pair("CMD_POLARITY"),
            corr_add=pair("CORR_ADD"),
            corr_subtract=pair("CORR_POLARITY"),
            pulse_clear=Pair(m("A_PULSE_CLEAR"), m("B_PULSE_CLEAR")),
            torque=pair("TORQUE"),
            select_shift=Pair(inputs.bit("AY_SELECT0"), inputs.bit("BX_SELECT0")),
            master_slave=m("MASTER_SLAVE"),
            brake_release=m("BRAKE_RELEASE"),
            error_reset=m("ERROR_RESET"),
            travel_model=c("TRAVEL_MODEL"),
            ready=pair("READY", control) if has_status else Pair(0, 0),
            busy=pair("BUSY", control) if has_status else Pair(0, 0),
        )

    # ------------------------------------------------------------ words by role

    @property
    def words(self) -> Mapping[str, FlagWord]:
        """Every word by the name state, events and recordings use for it."""
        return {
            "inputs": self.input,
            "control": self.control,
            "io": self.io,
            "error": FAULT,
            "alarm": FAULT,
        }

    # ------------------------------------------------------------ data select

    @property
    def select_mask(self) -> int:
        return 7 << self.select_shift.ay | 7 << self.select_shift.bx

    def select(self, ay: int, bx: int) -> int:
        """The input bits writing data-select values ``ay``, ``bx`` (0–7; 7 = set #0)."""
        return (ay & 7) << self.select_shift.ay | (bx & 7) << self.select_shift.bx

    def data_select(self, word: int) -> Pair:
        """The written 3-bit data-select values; the drive uses set ``7 - value``."""
        return Pair(word >> self.select_shift.ay & 7, word >> self.select_shift.bx & 7)

    # ------------------------------------------------------------ words the host writes

    def idle(self, ay_select: int, bx_select: int, torque: bool) -> int:
        """The word before any command: data select as configured, servo and start off."""
        return self.select(ay_select, bx_select) | (self.torque.both if torque else 0)

    def safe(self, inputs: int) -> int:
        """The way-out word: everything off but data select, which only picks a table.

        SERVO, START, brake release, torque, direction, correction, pulse clear, error
        reset and master/slave are all cleared.
        """
        return inputs & self.select_mask

    def undefined(self, data: int) -> int:
        """Bits of ``data`` this generation's input word does not define."""
        return data & ~self.input.defined & 0xFFFFFFFF


LAYOUT_2021 = Layout.build(
    Generation.G2021,
    _INPUT_2021,
    [(27, "TRAVEL_MODEL", "travel/turn model (0 = motor axes)", "走行軸モデル")],
    _IO_2021,
    brd1_inputs=False,
)
LAYOUT_2023 = Layout.build(
    Generation.G2023, _INPUT_2023, _CONTROL_ONLY_2023, _IO_2023, brd1_inputs=True
)
LAYOUTS: Mapping[Generation, Layout] = {
    Generation.G2021: LAYOUT_2021,
    Generation.G2023: LAYOUT_2023,
}


def layout(generation: Generation) -> Layout:
    return LAYOUTS[generation]


# The word a drive gets until its replies show its generation (core/readiness.py): A/Y data
# select 7 (set #0), the only bits that mean the same harmless thing in both layouts — the
# 2023 B/X data select bits are the 2021 B/X SERVO and START, and the 2021 ones the 2023
# torque and master/slave bits. A 2023 drive reports it in its control word; a 2021 drive's
# reply to it at rest is all zeros, so it identifies either.
ID_PROBE = LAYOUT_2021.select(7, 0) & LAYOUT_2023.select(7, 0)
assert ID_PROBE == LAYOUT_2021.select(7, 0) == LAYOUT_2023.select(7, 0)
