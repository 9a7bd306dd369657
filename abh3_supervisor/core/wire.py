"""CAN 2.0B extended-frame bit counts on the wire, for the planner and the bus model.

A frame is SOF, 29-bit identifier with SRR/IDE/RTR, r1 r0, DLC, data, CRC-15 (all of which
are bit-stuffed: a complementary bit after five equal ones), then CRC delimiter, ACK slot
and delimiter, 7-bit EOF and 3-bit intermission, which are not stuffed.
"""

from __future__ import annotations

UNSTUFFED_TAIL = 1 + 2 + 7 + 3  # CRC delimiter, ACK slot + delimiter, EOF, intermission


def stuffed_region_bits(dlc: int) -> int:
    return 1 + 11 + 1 + 1 + 18 + 1 + 2 + 4 + 8 * dlc + 15


def worst_case_bits(dlc: int) -> int:
    """Upper bound: every fourth bit after the first needs a stuff bit (8 bytes: 160)."""
    region = stuffed_region_bits(dlc)
    return region + (region - 1) // 4 + UNSTUFFED_TAIL


def _crc15(bits: list[int]) -> int:
    crc = 0
    for bit in bits:
        feedback = bit ^ (crc >> 14 & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= 0x4599
    return crc


def exact_bits(arbitration_id: int, data: bytes) -> int:
    """Bits this exact extended data frame occupies on the wire, stuffing included."""
    bits = [0]  # SOF
    bits += [arbitration_id >> (28 - i) & 1 for i in range(11)]
    bits += [1, 1]  # SRR, IDE
    bits += [arbitration_id >> (17 - i) & 1 for i in range(18)]
    bits += [0, 0, 0]  # RTR, r1, r0
    bits += [len(data) >> (3 - i) & 1 for i in range(4)]
    for byte in data:
        bits += [byte >> (7 - i) & 1 for i in range(8)]
    crc = _crc15(bits)
    bits += [crc >> (14 - i) & 1 for i in range(15)]
    stuff, run, last = 0, 0, -1
    for bit in bits:
        if bit == last:
            run += 1
        else:
            run, last = 1, bit
        if run == 5:  # a stuff bit of the opposite value follows and starts a new run
            stuff += 1
            run, last = 1, 1 - bit
    return len(bits) + stuff + UNSTUFFED_TAIL
