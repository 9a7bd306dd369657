"""The seed's input-service command language, parsed strictly.

``SERVO a b``, ``START``, ``DIR``, ``CADD``, ``CDIR``, ``PCLR``, ``TORQUE``, ``M/S``,
``BRAKE``, ``RESET`` take ``ON``/``OFF``/``1``/``0`` per axis (the last three are one bit,
so A and B must agree); ``SELECT a b`` takes the written data-select value 0–7 per axis.
Extensions of ours (not in the seed): ``VEL ay bx`` [min⁻¹] and ``CUR ay bx`` [%].
Keywords are case-insensitive; the token count and every value are checked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol import flags

# Service responses, exactly as the seed's ros2ABH3Cmd answers (manual §2.5).
RESPONSE_OK = ""
RESPONSE_INVALID = "Invalid Command."


def packet_error(code: int) -> str:
    return f"Packet Error: {code}"


# Our Packet Error codes (the seed prints its own errno-like value; ours are documented).
PACKET_NO_REPLY = 1  # the drive did not answer within the unit's timeout
PACKET_SEND_FAILED = 2  # the bus refused the frame
PACKET_ESTOP = 3  # refused: the emergency stop is latched


@dataclass(frozen=True, slots=True)
class InputChange:
    data: int
    mask: int


@dataclass(frozen=True, slots=True)
class VelocityCommand:
    ay: float
    bx: float


@dataclass(frozen=True, slots=True)
class CurrentCommand:
    ay: float
    bx: float


Command = InputChange | VelocityCommand | CurrentCommand

_M = flags.INPUT.mask
# keyword → (A/Y bit mask, B/X bit mask); single-bit commands use one mask for both
_PAIRS: dict[str, tuple[int, int]] = {
    "SERVO": (_M("AY_SERVO_ON"), _M("BX_SERVO_ON")),
    "START": (_M("AY_START"), _M("BX_START")),
    "DIR": (_M("AY_CMD_POLARITY"), _M("BX_CMD_POLARITY")),
    "CADD": (_M("AY_CORR_ADD"), _M("BX_CORR_ADD")),
    "CDIR": (_M("AY_CORR_POLARITY"), _M("BX_CORR_POLARITY")),
    "PCLR": (_M("A_PULSE_CLEAR"), _M("B_PULSE_CLEAR")),
    "TORQUE": (_M("AY_TORQUE"), _M("BX_TORQUE")),
}
_SINGLE: dict[str, int] = {
    "M/S": _M("SLAVE"),
    "BRAKE": _M("BRAKE_RELEASE"),
    "RESET": _M("ERROR_RESET"),
}
_SWITCH = {"ON": True, "1": True, "OFF": False, "0": False}
KEYWORDS = (*_PAIRS, *_SINGLE, "SELECT", "VEL", "CUR")


def _switch(token: str) -> bool:
    try:
        return _SWITCH[token.upper()]
    except KeyError:
        raise CommandError(f"'{token}' is not ON, OFF, 1 or 0") from None


def _number(token: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise CommandError(f"'{token}' is not a number") from None
    if not math.isfinite(value):
        raise CommandError(f"'{token}' is not a finite number")
    return value


def parse_command(text: str) -> Command:
    """Parse one command; raise :class:`CommandError` saying what is wrong."""
    tokens = text.split()
    if not tokens:
        raise CommandError("empty command")
    keyword = tokens[0].upper()
    if keyword not in KEYWORDS:
        raise CommandError(f"unknown command '{tokens[0]}' (known: {', '.join(KEYWORDS)})")
    if len(tokens) != 3:
        raise CommandError(f"{keyword} takes two values (A/Y and B/X), got {len(tokens) - 1}")
    a, b = tokens[1], tokens[2]
    if keyword in _PAIRS:
        mask_a, mask_b = _PAIRS[keyword]
        return InputChange(
            (mask_a if _switch(a) else 0) | (mask_b if _switch(b) else 0), mask_a | mask_b
        )
    if keyword in _SINGLE:
        on_a, on_b = _switch(a), _switch(b)
        if on_a != on_b:
            raise CommandError(f"{keyword} is one bit for both axes: give the same value twice")
        return InputChange(_SINGLE[keyword] if on_a else 0, _SINGLE[keyword])
    if keyword == "SELECT":
        sel_a, sel_b = _select(a), _select(b)
        return InputChange(
            sel_a << flags.AY_SELECT_SHIFT | sel_b << flags.BX_SELECT_SHIFT,
            7 << flags.AY_SELECT_SHIFT | 7 << flags.BX_SELECT_SHIFT,
        )
    if keyword == "VEL":
        return VelocityCommand(_number(a), _number(b))
    return CurrentCommand(_number(a), _number(b))


def _select(token: str) -> int:
    if token.isdigit() and 0 <= int(token) <= 7:
        return int(token)
    raise CommandError(f"'{token}' is not a data select value 0–7")
