"""TelABH3, the drive's string command protocol (params reference §1.1–1.2): pure codec.

A request is ``[FFFF] CMD ADDR [VALUE] SUM`` in ASCII, padded with SYN for the J1939
transport; a reply is ``[STX] [header] ACK|NAK DATA SUM [ETX]``. What the string on CAN
looks like exactly (with or without the ``FFFF`` header, and whether the checksum counts
the header when it is left out) is not settled by the public sources (§1.3): it is the
per-unit :class:`TelFormat`; replies are accepted in every form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal
from enum import StrEnum

from abh3_supervisor.errors import CodecError

HEADER = "FFFF"
STX, ETX, ACK, NAK, SYN = 0x02, 0x03, 0x06, 0x15, 0x16
MIN_TRANSPORT = 9  # J1939 TP carries at least 9 bytes (§1.3)


class Command(StrEnum):
    PARAM = "CP"  # parameter read (no value) / write (with value)
    MONITOR = "CM"  # monitor read
    IDENTITY = "BI"  # identity read: text


class Checksum(StrEnum):
    WITH_HEADER = "with_header"  # as if "FFFF" were sent (the only CAN example: CP000095)
    AS_SENT = "as_sent"  # over exactly the characters sent


@dataclass(frozen=True, slots=True)
class TelFormat:
    """How a unit's requests are written on CAN. Default: the maker's DLL example."""

    header: bool = False
    checksum: Checksum = Checksum.WITH_HEADER


DEFAULT_FORMAT = TelFormat()
# The three strings a request can be on CAN (header and checksum rule; a header always
# counts in the checksum), in the order a unit without a ``telabh3:`` setting tries them:
# the maker's only CAN example first (CP000095), then the serial form, then the checksum
# over exactly what is sent.
FORMS = (DEFAULT_FORMAT, TelFormat(header=True), TelFormat(False, Checksum.AS_SENT))


def wire_form(fmt: TelFormat) -> TelFormat:
    """The form as it is on the wire: with the header the checksum always counts it, so
    ``{header: true, checksum: as_sent}`` is the serial form, one of :data:`FORMS`."""
    return TelFormat(True) if fmt.header else fmt


def pin(fmt: TelFormat) -> str:
    """The unit's YAML setting that pins ``fmt``: ``telabh3: {header: false, ...}``."""
    fmt = wire_form(fmt)
    return f"telabh3: {{header: {str(fmt.header).lower()}, checksum: {fmt.checksum.value}}}"


def form_name(fmt: TelFormat) -> str:
    """``CP000095`` and its words: what the form looks like for a parameter read of 0."""
    example = Request(Command.PARAM, 0).text(fmt)
    if fmt.header:
        return f"{example} (the serial form: FFFF header)"
    rule = "counting FFFF" if fmt.checksum is Checksum.WITH_HEADER else "over what is sent"
    return f"{example} (no header, checksum {rule})"


def checksum(text: str) -> int:
    """``(-sum(ASCII codes)) & 0xFF`` (§1.1): ``checksum("FFFFCP0000") == 0x95``."""
    return -sum(text.encode("ascii")) & 0xFF


@dataclass(frozen=True, slots=True)
class Request:
    command: Command
    address: int
    value: int | None = None  # a write (CP only): the 32-bit word

    def __post_init__(self) -> None:
        if not 0 <= self.address <= 0xFFFF:
            raise CodecError(f"address {self.address:#x} is not 0x0000-0xFFFF")
        if self.value is not None and (self.command is not Command.PARAM):
            raise CodecError(f"{self.command.value} takes no value: only CP writes")
        if self.value is not None and not 0 <= self.value <= 0xFFFFFFFF:
            raise CodecError(f"value {self.value:#x} is not a 32-bit word")

    def text(self, fmt: TelFormat = DEFAULT_FORMAT) -> str:
        """The request string without SYN, e.g. ``CP000095`` (default format)."""
        body = f"{self.command.value}{self.address:04X}"
        if self.value is not None:
            body += f"{self.value:08X}"
        return _framed(body, fmt)

    def encode(self, fmt: TelFormat = DEFAULT_FORMAT) -> bytes:
        """The transport payload: at least one SYN, at least 9 bytes (§1.3)."""
        return _padded(self.text(fmt))


def _framed(body: str, fmt: TelFormat) -> str:
    """``body`` with the format's optional header and its checksum."""
    summed = HEADER + body if fmt.header or fmt.checksum is Checksum.WITH_HEADER else body
    return f"{HEADER if fmt.header else ''}{body}{checksum(summed):02X}"


def _padded(text: str) -> bytes:
    """A string on the transport: SYN after it, up to the transport's 9 bytes (§1.3)."""
    raw = text.encode("ascii") + bytes([SYN])
    return raw + bytes([SYN]) * (MIN_TRANSPORT - len(raw))


def decode_request(payload: bytes) -> tuple[Request, TelFormat]:
    """The drive's side: a request in any accepted form, and the form it came in."""
    try:
        text = _strip(payload).decode("ascii")
    except UnicodeDecodeError:
        raise CodecError("request is not ASCII") from None
    header = text.startswith(HEADER)
    body, sent_sum = (text[4:] if header else text)[:-2], text[-2:]
    try:
        total = int(sent_sum, 16)
    except ValueError:
        raise CodecError(f"request {text!r}: checksum {sent_sum!r} is not hex") from None
    if header:
        rule = Checksum.WITH_HEADER
        ok = checksum(HEADER + body) == total
    elif checksum(HEADER + body) == total:
        rule = Checksum.WITH_HEADER
        ok = True
    else:
        rule, ok = Checksum.AS_SENT, checksum(body) == total
    if not ok:
        raise CodecError(f"request {text!r}: bad checksum")
    if len(body) not in (6, 14):
        raise CodecError(f"request {text!r}: expected CMD ADDR [VALUE]")
    try:
        command = Command(body[:2])
        address = int(body[2:6], 16)
        value = int(body[6:], 16) if len(body) == 14 else None
    except ValueError as exc:
        raise CodecError(f"request {text!r}: {exc}") from None
    return Request(command, address, value), TelFormat(header, rule)


@dataclass(frozen=True, slots=True)
class Reply:
    ok: bool  # ACK (True) or NAK
    data: str  # 8 hex digits (a read), "" (a write), text (BI), or a NAK's detail

    @property
    def word(self) -> int:
        """A read's 32-bit word."""
        try:
            return int(self.data, 16) & 0xFFFFFFFF if len(self.data) == 8 else _bad(self.data)
        except ValueError:
            return _bad(self.data)


def _bad(data: str) -> int:
    raise CodecError(f"reply data {data!r} is not an 8-digit hex word")


def encode_reply(reply: Reply, fmt: TelFormat = DEFAULT_FORMAT) -> bytes:
    """The drive's reply in the form of the request it answers, SYN-padded like it."""
    return _padded(_framed(chr(ACK if reply.ok else NAK) + reply.data, fmt))


def decode_reply(payload: bytes) -> Reply:
    """A reply in any form: optional STX/ETX and 4-character header; the checksum must sum
    to zero over what was sent, or over it with ``FFFF`` in front (§1.1, §1.3)."""
    raw = _strip(payload)
    if raw[:1] == bytes([STX]):
        raw = raw[1:]
    if raw[-1:] == bytes([ETX]):
        raw = raw[:-1]
    mark = next((i for i, b in enumerate(raw) if b in (ACK, NAK)), -1)
    if mark not in (0, 4) or len(raw) < mark + 3:
        raise CodecError(f"reply {raw!r}: no ACK/NAK where expected")
    try:
        text = raw.decode("ascii")
        total = int(text[-2:], 16)
    except (UnicodeDecodeError, ValueError):
        raise CodecError(f"reply {raw!r}: not ASCII with a hex checksum") from None
    summed = text[:-2]
    if checksum(summed) != total and (mark or checksum(HEADER + summed) != total):
        raise CodecError(f"reply {text!r}: bad checksum")
    return Reply(raw[mark] == ACK, text[mark + 1 : -2])


def _strip(payload: bytes) -> bytes:
    """Trailing SYN and 0xFF are padding (§1.3)."""
    return payload.rstrip(bytes([SYN, 0xFF]))


# ------------------------------------------------------------ packed float (§1.2)

MANTISSA_BITS, POINT_BITS, EXPONENT_BITS = 21, 4, 7
POS_INF, NEG_INF = 0x0FFFFF, 0x100000  # mantissa codes
NAN_MANTISSA = 1_000_000  # any other |mantissa| > 999999
MAX_MANTISSA = 999_999


def signed(value: int, bits: int) -> int:
    """A ``bits``-wide two's-complement field as a Python int."""
    return value - (1 << bits) if value >> (bits - 1) & 1 else value


def unpack_float(word: int) -> float:
    """``0x00400008`` → 800.0; mantissa codes give ±inf and NaN."""
    raw_mantissa = word & 0x1FFFFF
    if raw_mantissa == POS_INF:
        return math.inf
    if raw_mantissa == NEG_INF:
        return -math.inf
    mantissa = signed(raw_mantissa, MANTISSA_BITS)
    if abs(mantissa) > MAX_MANTISSA:
        return math.nan
    point = signed(word >> 21 & 0xF, POINT_BITS)
    exponent = signed(word >> 25 & 0x7F, EXPONENT_BITS)
    return float(Decimal(mantissa).scaleb(exponent + point))


def pack_float(value: float) -> int:
    """The shortest form, trailing zeros into the point: 800 → ``0x00400008`` (as the
    maker's code writes it); six significant digits at most (rounded half-even)."""
    if math.isnan(value):
        return NAN_MANTISSA
    if math.isinf(value):
        return POS_INF if value > 0 else NEG_INF
    if value == 0:
        return 0
    d = Decimal(repr(value))
    digits = d.adjusted() + 1  # digits before the decimal point
    d = round(d, 6 - digits).normalize()  # at most six significant digits
    sign, figures, power = d.as_tuple()
    assert isinstance(power, int)
    mantissa = int("".join(map(str, figures))) * (-1 if sign else 1)
    point = max(-8, min(7, power))
    exponent = power - point
    if not -64 <= exponent <= 63:
        raise CodecError(f"{value!r} is beyond the packed-float range")
    return (exponent & 0x7F) << 25 | (point & 0xF) << 21 | (mantissa & 0x1FFFFF)
