"""The maker's USB-CAN adapter's serial framing (params-and-usbcan doc §2), pure functions.

``STX FLAG(2 hex) ID(8 hex) DATA(2×DLC hex) CRC(4 hex) ETX``: FLAG bit 4 = extended id,
bits 3–0 = DLC, bit 7 = a 16-hex timestamp follows FLAG (the maker's DLL accepts it; the
published firmware never sends it). The CRC is CRC-16/CCITT (poly 0x1021, MSB first, init
0xFFFF, final XOR 0xFFFF) over the ASCII characters from FLAG to the end of DATA — the
README's "0x8408" does not match the firmware's code.
"""

from __future__ import annotations

from dataclasses import dataclass

STX, ETX = 0x02, 0x03
FLAG_EXTENDED = 0x10
FLAG_TIMESTAMP = 0x80
DLC_MASK = 0x0F
# the longest frame: FLAG, timestamp, ID, 8 data bytes, CRC (STX/ETX excluded)
MAX_BODY = 2 + 16 + 8 + 16 + 4


def _table() -> tuple[int, ...]:
    rows = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = (crc << 1 ^ 0x1021) if crc & 0x8000 else crc << 1
        rows.append(crc & 0xFFFF)
    return tuple(rows)


_CRC_TABLE = _table()


def crc16(text: bytes) -> int:
    """The adapter's CRC over the ASCII text; ``b"1800EF0102C309C30900000000"`` → 0xCC4B."""
    crc = 0xFFFF
    for byte in text:
        crc = (crc << 8 & 0xFFFF) ^ _CRC_TABLE[(crc >> 8) ^ byte]
    return crc ^ 0xFFFF


def encode(arbitration_id: int, data: bytes, extended: bool = True) -> bytes:
    """One frame for the adapter, STX to ETX, upper-case hex as the firmware writes it."""
    if len(data) > 8:
        raise ValueError(f"{len(data)} data bytes: classic CAN carries at most 8")
    limit = 0x1FFFFFFF if extended else 0x7FF
    if not 0 <= arbitration_id <= limit:
        raise ValueError(
            f"identifier 0x{arbitration_id:X} does not fit a {limit.bit_length()}-bit id"
        )
    flag = (FLAG_EXTENDED if extended else 0) | len(data)
    body = f"{flag:02X}{arbitration_id:08X}{data.hex().upper()}".encode("ascii")
    return bytes([STX]) + body + f"{crc16(body):04X}".encode("ascii") + bytes([ETX])


@dataclass(frozen=True)
class Frame:
    arbitration_id: int
    data: bytes
    extended: bool
    timestamp: int | None = None  # the adapter's own, when FLAG bit 7 is set


class BadFrame(ValueError):
    """Between STX and ETX, but not a frame: ``crc`` tells a CRC mismatch from bad framing."""

    def __init__(self, why: str, *, crc: bool = False) -> None:
        super().__init__(why)
        self.crc = crc


def decode(body: bytes) -> Frame:
    """The text between STX and ETX; raises :class:`BadFrame`."""
    try:
        text = body.decode("ascii")
        flag = int(text[0:2], 16)
    except (UnicodeDecodeError, ValueError):
        raise BadFrame(f"not hex: {body[:40]!r}") from None
    if not all(c in "0123456789ABCDEFabcdef" for c in text):
        raise BadFrame(f"not hex: {body[:40]!r}")
    dlc = flag & DLC_MASK
    stamp = 16 if flag & FLAG_TIMESTAMP else 0
    if dlc > 8:
        raise BadFrame(f"DLC {dlc}")
    need = 2 + stamp + 8 + 2 * dlc + 4
    if len(text) != need:
        raise BadFrame(f"{len(text)} characters where FLAG {flag:02X} needs {need}")
    if int(text[-4:], 16) != crc16(body[:-4]):
        raise BadFrame(f"CRC {text[-4:]} ≠ {crc16(body[:-4]):04X}", crc=True)
    at = 2 + stamp
    return Frame(
        arbitration_id=int(text[at : at + 8], 16),
        data=bytes.fromhex(text[at + 8 : at + 8 + 2 * dlc]),
        extended=bool(flag & FLAG_EXTENDED),
        timestamp=int(text[2:at], 16) if stamp else None,
    )


class Parser:
    """Splits the adapter's byte stream into frames; resynchronises on every STX."""

    def __init__(self) -> None:
        self._body: bytearray | None = None  # None: between frames, waiting for STX
        self.crc_errors = 0
        self.framing_errors = 0
        self.last_error: str | None = None

    def feed(self, chunk: bytes) -> list[Frame]:
        frames: list[Frame] = []
        for byte in chunk:
            if byte == STX:
                if self._body is not None:  # a frame cut short: the adapter lost bytes
                    self._bad(BadFrame("STX inside a frame"))
                self._body = bytearray()
            elif self._body is None:
                continue  # noise between frames
            elif byte == ETX:
                body, self._body = bytes(self._body), None
                try:
                    frames.append(decode(body))
                except BadFrame as exc:
                    self._bad(exc)
            elif len(self._body) >= MAX_BODY:
                self._body = None
                self._bad(BadFrame("no ETX within the longest frame"))
            else:
                self._body.append(byte)
        return frames

    def _bad(self, exc: BadFrame) -> None:
        if exc.crc:
            self.crc_errors += 1
        else:
            self.framing_errors += 1
        self.last_error = str(exc)
