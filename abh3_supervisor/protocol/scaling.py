"""Physical units ↔ wire integers (protocol doc §4).

Round to nearest and clamp to the wire range: the vendor C sample truncates, which lands
one LSB low for values like 100 / 0.2. NaN and infinity are refused, never sent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from abh3_supervisor.errors import CodecError


@dataclass(frozen=True, slots=True)
class Scale:
    """One quantity's LSB and the integer range its field can hold."""

    name: str
    lsb: float
    raw_min: int
    raw_max: int
    unit: str

    @property
    def minimum(self) -> float:
        return self.raw_min * self.lsb

    @property
    def maximum(self) -> float:
        return self.raw_max * self.lsb

    @property
    def largest(self) -> float:
        """The largest magnitude the field holds (int16 reaches one LSB further below 0)."""
        return max(-self.minimum, self.maximum)

    def to_raw(self, value: float) -> tuple[int, bool]:
        """Return ``(raw, clamped)``; raise :class:`CodecError` on NaN or infinity."""
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise CodecError(f"{self.name}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise CodecError(f"{self.name}: {value} is not a finite number")
        raw = round(value / self.lsb)
        if raw < self.raw_min:
            return self.raw_min, True
        if raw > self.raw_max:
            return self.raw_max, True
        return raw, False

    def to_physical(self, raw: int) -> float:
        # round() strips binary noise such as 0.30000000000000004 from the decimal LSBs
        return round(raw * self.lsb, 6)


INT16 = (-0x8000, 0x7FFF)
UINT16 = (0, 0xFFFF)

VELOCITY = Scale("velocity", 0.2, *INT16, "min^-1")
CURRENT = Scale("current", 0.01, *INT16, "%")
# §4 disagreement: the spec table (and the vendor's later Python/Wireshark code) say
# 1 %/LSB; the 2021 C sample multiplies by 0.1. We follow the spec and keep the raw value
# in every decoded record so the other reading stays visible (LOAD_LSB_C_SAMPLE).
LOAD = Scale("load", 1.0, *UINT16, "%")
LOAD_LSB_C_SAMPLE = 0.1
SUPPLY_VOLTAGE = Scale("supply voltage", 0.1, *UINT16, "V")
ANALOG = Scale("analog input", 0.01, *INT16, "V")
