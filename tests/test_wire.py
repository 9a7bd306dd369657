"""Bit counts of CAN 2.0B extended frames on the wire."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from abh3_supervisor.core.wire import (
    UNSTUFFED_TAIL,
    exact_bits,
    stuffed_region_bits,
    worst_case_bits,
)


def test_worst_case_lengths() -> None:
    assert worst_case_bits(8) == 160
    assert worst_case_bits(3) == 110
    assert stuffed_region_bits(8) + UNSTUFFED_TAIL == 131  # no stuff bits at all


def test_runs_of_equal_bits_cost_stuff_bits() -> None:
    zeros = exact_bits(0x00EF0102, bytes(8))
    alternating = exact_bits(0x00EF0102, bytes([0x55] * 8))
    assert alternating < zeros <= 160
    assert alternating >= 131


@given(st.integers(min_value=0, max_value=0x1FFFFFFF), st.binary(max_size=8))
def test_exact_is_between_unstuffed_and_worst_case(arbitration_id: int, data: bytes) -> None:
    bits = exact_bits(arbitration_id, data)
    assert stuffed_region_bits(len(data)) + UNSTUFFED_TAIL <= bits <= worst_case_bits(len(data))
