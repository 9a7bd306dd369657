"""Parameter, monitor and identity addresses with readable names (params reference §1.4).

Data, not code: what the public sources name. ``kind`` says how the 32-bit word reads:
``pf`` the packed float (§1.2), ``int`` a plain signed 32-bit integer (pulse counts, flag
words). Which settings are flag words is our reading of the maker's parameter file; the
``default`` is the simulator's value (the AGV file's where the reference gives one).
Addresses not listed here are shown as hex.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

from abh3_supervisor.errors import CodecError
from abh3_supervisor.params.telabh3 import pack_float, signed, unpack_float

Kind = Literal["pf", "int"]


@dataclass(frozen=True, slots=True)
class Entry:
    address: int
    name: str
    kind: Kind = "pf"
    default: float = 0.0


def _block(base: int, name: str, values: list[float], kind: Kind = "pf") -> list[Entry]:
    return [Entry(base + i, f"{name}_{i}", kind, v) for i, v in enumerate(values)]


_SPEEDS = [800.0, 400.0, 200.0, 100.0, 50.0, 20.0, 10.0, 0.0]
PARAMETERS: tuple[Entry, ...] = (
    Entry(0x4100, "CAN_FUNCTION", default=2),  # 2 = CAN control
    Entry(0x4101, "CAN_BITRATE", default=500),
    Entry(0x4102, "CAN_ABH3_ADDRESS", default=1),
    Entry(0x4103, "CAN_HOST_ADDRESS", default=-1),  # −1 = any host
    Entry(0x4105, "CAN_DP0_REPLY_MODE", default=0),  # −1 none, 0 on receipt, 1–1000 ms
    Entry(0x4107, "CAN_BROADCAST_GROUP", default=5),
    *_block(0x4108, "CAN_BROADCAST_PERIOD", [0.0] * 8),  # ms, 0 = on request only
    *_block(0x4110, "CAN_RECEIVE_BROADCAST", [0.0] * 4),
    *_block(0x4114, "CAN_PRIORITY", [0.0] * 3),
    Entry(0x4117, "CAN_COMMAND_ZERO_TIMEOUT", default=750),  # ms
    Entry(0x4118, "CAN_ERROR_TIMEOUT", default=2000),  # ms
    Entry(0x4119, "CAN_MULTIPACKET_DT_WAIT", default=0),  # ms between the drive's DTs
    Entry(0x411A, "CAN_CONTROL_FLAG_LOGIC", "int"),
    *_block(0x5000, "SPEED_AY", _SPEEDS),
    *_block(0x5008, "SPEED_BX", _SPEEDS),
    *_block(0x5010, "CURRENT_AY", [100.0] * 8),
    *_block(0x5018, "CURRENT_BX", [100.0] * 8),
    # where the B/X entries of the next blocks sit is not certain (§1.4): A/Y only
    *_block(0x5020, "ACCEL_AY", [0.25] * 8),
    *_block(0x5030, "S_CURVE_AY", [0.1] * 8),
    *_block(0x5040, "DECEL_AY", [0.25] * 8),
    *_block(0x5050, "DECEL_S_CURVE_AY", [0.1] * 8),
    *_block(0x5060, "KP_AY", [50.0] * 8),
    *_block(0x5070, "KI_AY", [20.0] * 8),
    Entry(0x50E0, "DATA_SELECT_SOURCE_AY", default=2),  # 0 internal, 2 CAN
    Entry(0x50F0, "DATA_SELECT_SOURCE_BX", default=2),
    Entry(0x5100, "INPUT_ASSIGN_A", "int"),
    Entry(0x5120, "INPUT_ASSIGN_B", "int"),
    Entry(0x51A0, "ANALOG_INPUT_CALIBRATION"),
    *_block(0x5180, "DIGITAL_OUTPUT", [0.0] * 8, "int"),
    Entry(0x51C0, "ANALOG_MONITOR_0"),
    Entry(0x51D0, "ANALOG_MONITOR_1"),
    Entry(0x6180, "CAN_DP0_PDU_FORMAT", default=239),
)

MONITORS: tuple[Entry, ...] = (
    Entry(0x0000, "ALARMS", "int"),
    Entry(0x0001, "WARNINGS", "int"),
    Entry(0x0002, "INPUTS", "int"),
    Entry(0x0003, "INPUT_CONTROL", "int"),
    Entry(0x0004, "OUTPUTS", "int"),  # bits 24–31 = DOUT0–7
    Entry(0x0005, "OUTPUT_CONTROL", "int"),
    Entry(0x1004, "MAIN_VOLTAGE"),
    Entry(0x1005, "CONTROL_VOLTAGE"),
    Entry(0x1012, "VELOCITY_AY"),
    Entry(0x1022, "VELOCITY_BX"),
    Entry(0x1031, "CURRENT_A"),
    Entry(0x1041, "CURRENT_B"),
    Entry(0x103B, "LOAD_A"),
    Entry(0x104B, "LOAD_B"),
    Entry(0x1054, "PULSES_A", "int"),
    Entry(0x1064, "PULSES_B", "int"),
)

FIRMWARE_VERSION = 0x2  # the identity (BI) address the maker's tool shows as the version
IDENTITY: dict[int, str] = {
    0x0: "",
    FIRMWARE_VERSION: "FIRMWARE_VERSION",
    0x4: "",
    0x5: "",
    0x8: "",
    0xC: "",
}

BY_ADDRESS = {e.address: e for e in PARAMETERS}
BY_NAME = {e.name: e for e in PARAMETERS}
MONITOR_BY_ADDRESS = {e.address: e for e in MONITORS}
MONITOR_BY_NAME = {e.name: e for e in MONITORS}


def label(address: int, monitor: bool = False) -> str:
    entry = (MONITOR_BY_ADDRESS if monitor else BY_ADDRESS).get(address)
    return entry.name if entry is not None else f"0x{address:04X}"


def parse_address(text: str, monitor: bool = False) -> int:
    """A name (``SPEED_AY_0``), hex (``0x5000``, ``5000h``) or decimal (``20480``, as in
    the maker's CSV)."""
    names = MONITOR_BY_NAME if monitor else BY_NAME
    key = text.strip().upper()
    if key in names:
        return names[key].address
    try:
        if key.startswith("0X"):
            value = int(key[2:], 16)
        elif key.endswith("H"):
            value = int(key[:-1], 16)
        else:
            value = int(key, 10)
    except ValueError:
        what, example = (
            ("monitor", "MAIN_VOLTAGE or 0x1004") if monitor else ("parameter", "0x5000")
        )
        raise CodecError(f"'{text}' is no {what} name or address (e.g. {example})") from None
    if not 0 <= value <= 0xFFFF:
        raise CodecError(f"address {text} is not 0x0000-0xFFFF")
    return value


def kind_of(address: int, monitor: bool = False) -> Kind:
    entry = (MONITOR_BY_ADDRESS if monitor else BY_ADDRESS).get(address)
    return entry.kind if entry is not None else "pf"


def to_value(word: int, kind: Kind) -> float:
    """The physical value of a 32-bit word."""
    if kind == "int":
        return float(signed(word, 32))
    return unpack_float(word)


def to_word(value: float, kind: Kind) -> int:
    """The word the drive is sent for ``value``; refused (:class:`CodecError`) unless the
    word means that value: NaN and infinities never (a packed float has codes for them,
    but no setting wants one, and ``set nan`` is a typo); an ``int`` must be a whole number
    within 32 bits (signed or unsigned); a packed float is rounded to six significant
    digits and must come back the same within that rounding — one beyond the format's
    range (about 1e-72 to 1e76) is refused, never written as another magnitude."""
    if kind == "int":
        if not math.isfinite(value) or value != int(value) or not INT_MIN <= value <= WORD_MAX:
            raise CodecError(f"{value!r} is not a 32-bit integer")
        return int(value) & WORD_MAX
    if not math.isfinite(value):
        raise CodecError(f"{value!r} is not a finite number: NaN and infinities are refused")
    word = pack_float(value)  # CodecError beyond the exponent's range
    back = unpack_float(word)
    if not math.isclose(back, value, rel_tol=PF_ROUNDING):
        raise CodecError(f"{value!r} does not fit a packed float (it would be {back!r})")
    return word


INT_MIN, WORD_MAX = -(2**31), 2**32 - 1  # an internal value: signed or unsigned 32 bits
PF_ROUNDING = 5.000001e-6  # six significant digits, rounded: at most half a unit of the 6th
_WORD = re.compile(r"[+-]?[0-9]+|0[xX][0-9a-fA-F]+")
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_word(text: str) -> int:
    """An internal value as files write it: decimal (signed ``-2147483648`` … unsigned
    ``4294967295``) or ``0x`` hex up to ``0xFFFFFFFF``; anything else is refused, never
    masked to 32 bits."""
    key = text.strip()
    if not _WORD.fullmatch(key):
        raise CodecError(f"{quote(text)} is not an integer (decimal or 0x hex)")
    value = int(key, 16) if key[:2] in ("0x", "0X") else int(key, 10)
    if not INT_MIN <= value <= WORD_MAX:
        raise CodecError(f"{quote(text)} is beyond 32 bits (-2147483648 to 4294967295)")
    return value & WORD_MAX


def quote(text: str) -> str:
    """A value quoted for a message: control characters escaped, at most 40 characters."""
    shown = text if text.isprintable() else text.encode("unicode_escape").decode("ascii")
    return f"'{shown if len(shown) <= 40 else shown[:37] + '...'}'"


def parse_number(text: str) -> float | None:
    """A display value that is a plain decimal number (``800``, ``-0.25``, ``1e3``), or
    None for anything else (a unit after it, a word: the maker's tool writes both)."""
    key = text.strip()
    return float(key) if _NUMBER.fullmatch(key) else None


def display(value: float) -> str:
    """``800``, ``0.25``, ``inf``: integers without a point, the shortest form otherwise."""
    if math.isfinite(value) and value == int(value):
        return str(int(value))
    return repr(value)
