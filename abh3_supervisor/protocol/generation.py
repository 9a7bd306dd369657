"""The two ABH3 protocol generations (protocol doc §3.1, §5)."""

from __future__ import annotations

from enum import StrEnum


class Generation(StrEnum):
    """2021 is the seed's protocol; 2023 is the "new CAN specification"."""

    G2021 = "2021"
    G2023 = "2023"
