"""Frame payloads (protocol doc §3.1–3.3) for both protocol generations.

Encoders take wire integers (see :mod:`.scaling` for physical → wire); decoders return
typed records in physical units and never raise: a malformed payload decodes to
:class:`Unknown` with the reason.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from abh3_supervisor.protocol.flags import layout
from abh3_supervisor.protocol.generation import Generation as Generation
from abh3_supervisor.protocol.ids import PF_BROADCAST, PF_SINGLE
from abh3_supervisor.protocol.scaling import ANALOG, CURRENT, LOAD, SUPPLY_VOLTAGE, VELOCITY

_HHI = struct.Struct("<hhI")  # DP0 command, 2023 reply
_HHHH = struct.Struct("<hhhh")  # 2021 reply, broadcast 2
_II = struct.Struct("<II")  # broadcast 0, 1
_HHHH_U = struct.Struct("<hhHH")  # broadcast 3, 5
_III = struct.Struct("<ii")  # broadcast 4
_FF = struct.Struct("<ff")  # broadcast 6
_PGN = struct.Struct("<HB")

PGN_DP0 = PF_SINGLE << 8  # 0x00EF00: "send me a DP0 reply" (§3.2)


def broadcast_pgn(group: int, packet: int) -> int:
    return PF_BROADCAST << 8 | (group * 8 + packet)


@dataclass(frozen=True, slots=True)
class Unknown:
    reason: str


@dataclass(frozen=True, slots=True)
class Dp0Command:
    """Host → drive. A field is a current (%) when its axis's torque bit is set."""

    cmd_ay: float
    cmd_bx: float
    inputs: int
    ay_is_current: bool = False
    bx_is_current: bool = False


@dataclass(frozen=True, slots=True)
class Dp0Reply2021:
    vel_a: float
    vel_b: float
    vel_y: float
    vel_x: float


@dataclass(frozen=True, slots=True)
class Dp0Reply2023:
    vel_ay: float
    vel_bx: float
    control: int


Dp0Reply = Dp0Reply2021 | Dp0Reply2023


@dataclass(frozen=True, slots=True)
class Request:
    pgn: int

    @property
    def is_dp0(self) -> bool:
        return self.pgn == PGN_DP0

    @property
    def broadcast(self) -> tuple[int, int] | None:
        """``(group, packet)`` when this requests a broadcast packet."""
        if self.pgn >> 8 == PF_BROADCAST:
            return (self.pgn & 0xFF) >> 3, self.pgn & 7
        return None


@dataclass(frozen=True, slots=True)
class Brd0:
    error: int
    alarm: int


@dataclass(frozen=True, slots=True)
class Brd1:
    """2021: control + I/O flags; 2023: I/O + input flags. The absent word is ``None``."""

    io: int
    control: int | None = None
    inputs: int | None = None


@dataclass(frozen=True, slots=True)
class Brd2:
    vel_cmd_ay: float
    vel_cmd_bx: float
    vel_fbk_ay: float
    vel_fbk_bx: float


@dataclass(frozen=True, slots=True)
class Brd3:
    """Loads in % at the spec's 1 %/LSB; the raw values keep the C sample's 0.1 visible."""

    cur_cmd_ay: float
    cur_cmd_bx: float
    load_a: float
    load_b: float
    load_a_raw: int
    load_b_raw: int


@dataclass(frozen=True, slots=True)
class Brd4:
    pulse_a: int
    pulse_b: int


@dataclass(frozen=True, slots=True)
class Brd5:
    analog0: float
    analog1: float
    main_volt: float
    control_volt: float


@dataclass(frozen=True, slots=True)
class Brd6:
    monitor0: float
    monitor1: float


@dataclass(frozen=True, slots=True)
class Brd7:
    """Not defined by the spec; the raw bytes are kept."""

    raw: bytes


Broadcast = Brd0 | Brd1 | Brd2 | Brd3 | Brd4 | Brd5 | Brd6 | Brd7

# ---------------------------------------------------------------- encoders


def encode_dp0_command(cmd_ay: int, cmd_bx: int, inputs: int) -> bytes:
    return _HHI.pack(cmd_ay, cmd_bx, inputs & 0xFFFFFFFF)


def encode_request(pgn: int) -> bytes:
    return _PGN.pack(pgn & 0xFFFF, pgn >> 16 & 0xFF)


def encode_dp0_reply_2021(vel_a: int, vel_b: int, vel_y: int, vel_x: int) -> bytes:
    return _HHHH.pack(vel_a, vel_b, vel_y, vel_x)


def encode_dp0_reply_2023(vel_ay: int, vel_bx: int, control: int) -> bytes:
    return _HHI.pack(vel_ay, vel_bx, control & 0xFFFFFFFF)


def encode_words(first: int, second: int) -> bytes:
    """Broadcast 0 and 1: two 32-bit flag words."""
    return _II.pack(first & 0xFFFFFFFF, second & 0xFFFFFFFF)


def encode_int16x4(a: int, b: int, c: int, d: int) -> bytes:
    """Broadcast 2: four signed 16-bit fields."""
    return _HHHH.pack(a, b, c, d)


def encode_int16x2_uint16x2(a: int, b: int, c: int, d: int) -> bytes:
    """Broadcast 3 and 5: two signed then two unsigned 16-bit fields."""
    return _HHHH_U.pack(a, b, c, d)


def encode_pulses(pulse_a: int, pulse_b: int) -> bytes:
    return _III.pack(pulse_a, pulse_b)


def encode_monitors(monitor0: float, monitor1: float) -> bytes:
    return _FF.pack(monitor0, monitor1)


# ---------------------------------------------------------------- decoders


def _short(data: bytes, need: int, what: str) -> Unknown | None:
    """8-byte frames are exactly 8 (a longer one is CAN FD or garbage, never a reply);
    a request needs its 3 PGN bytes."""
    if len(data) < need or (need == 8 and len(data) != 8):
        return Unknown(f"{what}: {len(data)} data bytes, expected {need}")
    return None


def unpack_dp0_command(data: bytes) -> tuple[int, int, int]:
    """Wire integers (AY, BX, inputs) of an 8-byte DP0 command."""
    ay, bx, inputs = _HHI.unpack_from(data)
    return ay, bx, inputs


def decode_dp0_command(data: bytes, generation: Generation) -> Dp0Command | Unknown:
    """The torque bits of the drive's generation say whether a field is a current."""
    if bad := _short(data, 8, "DP0 command"):
        return bad
    ay, bx, inputs = _HHI.unpack_from(data)
    torque = layout(generation).torque
    current_ay, current_bx = bool(inputs & torque.ay), bool(inputs & torque.bx)
    return Dp0Command(
        (CURRENT if current_ay else VELOCITY).to_physical(ay),
        (CURRENT if current_bx else VELOCITY).to_physical(bx),
        inputs,
        current_ay,
        current_bx,
    )


def decode_dp0_reply(data: bytes, generation: Generation) -> Dp0Reply | Unknown:
    if bad := _short(data, 8, "DP0 reply"):
        return bad
    v = VELOCITY.to_physical
    if generation is Generation.G2023:
        ay, bx, control = _HHI.unpack_from(data)
        return Dp0Reply2023(v(ay), v(bx), control)
    a, b, y, x = _HHHH.unpack_from(data)
    return Dp0Reply2021(v(a), v(b), v(y), v(x))


def decode_request(data: bytes) -> Request | Unknown:
    if bad := _short(data, 3, "request"):
        return bad
    low, high = _PGN.unpack_from(data)
    return Request(high << 16 | low)


def decode_broadcast(packet: int, data: bytes, generation: Generation) -> Broadcast | Unknown:
    if packet == 7:
        return Brd7(bytes(data))
    if bad := _short(data, 8, f"broadcast {packet}"):
        return bad
    if packet == 0:
        return Brd0(*_II.unpack_from(data))
    if packet == 1:
        first, second = _II.unpack_from(data)
        if generation is Generation.G2023:
            return Brd1(io=first, inputs=second)
        return Brd1(io=second, control=first)
    if packet == 2:
        v = VELOCITY.to_physical
        return Brd2(*(v(raw) for raw in _HHHH.unpack_from(data)))
    if packet == 3:
        ca, cb, la, lb = _HHHH_U.unpack_from(data)
        c, load = CURRENT.to_physical, LOAD.to_physical
        return Brd3(c(ca), c(cb), load(la), load(lb), la, lb)
    if packet == 4:
        return Brd4(*_III.unpack_from(data))
    if packet == 5:
        a0, a1, main, ctrl = _HHHH_U.unpack_from(data)
        return Brd5(
            ANALOG.to_physical(a0),
            ANALOG.to_physical(a1),
            SUPPLY_VOLTAGE.to_physical(main),
            SUPPLY_VOLTAGE.to_physical(ctrl),
        )
    if packet == 6:
        m0, m1 = _FF.unpack_from(data)
        return Brd6(m0, m1)
    return Unknown(f"broadcast packet {packet} does not exist")
