"""The seed's input-service command language, parsed strictly.

``SERVO a b``, ``START``, ``DIR``, ``CADD``, ``CDIR``, ``PCLR``, ``TORQUE``, ``M/S``,
``BRAKE``, ``RESET`` take ``ON``/``OFF``/``1``/``0`` per axis (the last three are one bit,
so A and B must agree); ``SELECT a b`` takes the written data-select value 0–7 per axis.
Extensions of ours (not in the seed): ``VEL ay bx`` [min⁻¹] and ``CUR ay bx`` [%].
Keywords and ``ON``/``OFF`` are case-insensitive (``vel 50 0`` is ``VEL 50 0``, with the
same answer); the text is printable ASCII; the token count and every value are checked.
Parsing knows no bit positions: :func:`input_change` places a command in the unit's
generation's layout (protocol doc §5), so one command means the same on both.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from abh3_supervisor.errors import CommandError
from abh3_supervisor.protocol.flags import Layout, Pair

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
    """Raw input bits (the seed's ``inp_data``): ``mask`` selects the bits ``data`` sets."""

    data: int
    mask: int


@dataclass(frozen=True, slots=True)
class SwitchCommand:
    """``SERVO``, ``START``, …: one bit per axis, or one bit for both (``M/S``, ``BRAKE``,
    ``RESET``, where ``ay == bx``). Generation-free: :func:`input_change` places the bits.
    """

    keyword: str
    ay: bool
    bx: bool


@dataclass(frozen=True, slots=True)
class SelectCommand:
    """``SELECT a b``: the written data-select values (0 = set #7 & STOP … 7 = set #0)."""

    ay: int
    bx: int


@dataclass(frozen=True, slots=True)
class VelocityCommand:
    ay: float
    bx: float


@dataclass(frozen=True, slots=True)
class CurrentCommand:
    ay: float
    bx: float


Command = SwitchCommand | SelectCommand | InputChange | VelocityCommand | CurrentCommand

# keyword → the Layout mask it sets: a Pair (one bit per axis) or one bit for both axes
_PAIRS = {
    "SERVO": "servo",
    "START": "start",
    "DIR": "reverse",
    "CADD": "corr_add",
    "CDIR": "corr_subtract",
    "PCLR": "pulse_clear",
    "TORQUE": "torque",
}
_SINGLE = {"M/S": "master_slave", "BRAKE": "brake_release", "RESET": "error_reset"}
_SWITCH = {"ON": True, "1": True, "OFF": False, "0": False}
KEYWORDS = (*_PAIRS, *_SINGLE, "SELECT", "VEL", "CUR")
# ASCII only: str.split() and float() would accept Unicode spaces and digits ('²', '١')
_SPACE = re.compile(r"[ \t\r\n]+")
_PRINTABLE = re.compile(r"[\x20-\x7e\t\r\n]*")
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_MAX_LENGTH = 200  # far above any valid command; longer text is not parsed at all


def _switch(token: str) -> bool:
    try:
        return _SWITCH[token.upper()]
    except KeyError:
        raise CommandError(f"'{token}' is not ON, OFF, 1 or 0") from None


def _number(token: str) -> float:
    if not _NUMBER.fullmatch(token):
        raise CommandError(f"'{token}' is not a number")
    value = float(token)
    if not math.isfinite(value):
        raise CommandError(f"'{token}' is not a finite number")
    return value


def _select(token: str) -> int:
    if token in ("0", "1", "2", "3", "4", "5", "6", "7"):
        return int(token)
    raise CommandError(f"'{token}' is not a data select value 0–7")


def parse_command(text: str) -> Command:
    """Parse one command; raise :class:`CommandError` saying what is wrong."""
    if not isinstance(text, str):
        raise CommandError(f"a command is text, not {type(text).__name__}")
    if len(text) > _MAX_LENGTH:
        raise CommandError(f"command longer than {_MAX_LENGTH} characters")
    if not _PRINTABLE.fullmatch(text):
        raise CommandError("commands are printable ASCII: keywords, ON/OFF/1/0 and numbers")
    tokens = [t for t in _SPACE.split(text) if t]
    if not tokens:
        raise CommandError("empty command")
    keyword = tokens[0].upper()
    if keyword not in KEYWORDS:
        raise CommandError(f"unknown command '{tokens[0]}' (known: {', '.join(KEYWORDS)})")
    if len(tokens) != 3:
        raise CommandError(f"{keyword} takes two values (A/Y and B/X), got {len(tokens) - 1}")
    a, b = tokens[1], tokens[2]
    if keyword in _PAIRS:
        return SwitchCommand(keyword, _switch(a), _switch(b))
    if keyword in _SINGLE:
        on_a, on_b = _switch(a), _switch(b)
        if on_a != on_b:  # the manual: "give the same value"; the maker's code ORs them
            raise CommandError(f"{keyword} is one bit for both axes: give the same value twice")
        return SwitchCommand(keyword, on_a, on_b)
    if keyword == "SELECT":
        return SelectCommand(_select(a), _select(b))
    if keyword == "VEL":
        return VelocityCommand(_number(a), _number(b))
    return CurrentCommand(_number(a), _number(b))


def input_change(command: SwitchCommand | SelectCommand, layout: Layout) -> InputChange:
    """The input bits a command sets in one generation's layout (protocol doc §5)."""
    if isinstance(command, SelectCommand):
        return InputChange(layout.select(command.ay, command.bx), layout.select_mask)
    if command.keyword in _SINGLE:
        bit: int = getattr(layout, _SINGLE[command.keyword])
        return InputChange(bit if command.ay else 0, bit)
    pair: Pair = getattr(layout, _PAIRS[command.keyword])
    return InputChange((pair.ay if command.ay else 0) | (pair.bx if command.bx else 0), pair.both)
