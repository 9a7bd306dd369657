"""J1939 transport judged from the wire frames of a fake-clock timeline (J1939-21, not our machines)."""

from __future__ import annotations

import math

from abh3_supervisor.protocol import ids
from abh3_supervisor.simulator.timeline import WireFrame


def check_j1939(frames: list[WireFrame]) -> list[bytes]:
    """Walk every TP.CM/TP.DT frame (written from J1939-21, not from our machines) and
    return the messages each completed session carried; raise on any broken rule."""
    sessions: dict[tuple[int, int], dict[str, int | bytearray]] = {}
    done: list[bytes] = []
    for f in frames:
        pf, dst, src = (
            f.arbitration_id >> 16 & 0xFF,
            f.arbitration_id >> 8 & 0xFF,
            f.arbitration_id & 0xFF,
        )
        if pf not in (0xEC, 0xEB):
            continue
        assert len(f.data) == 8, f"TP frames carry 8 bytes: {f}"
        if pf == 0xEC:
            assert f.data[5:8] == b"\x00\xef\x00", f"signature missing: {f.data.hex()}"
            kind = f.data[0]
            if kind == 0x10:  # RTS src → dst
                assert (src, dst) not in sessions, "RTS while a session is open"
                length = f.data[1] | f.data[2] << 8
                assert length >= 9 and f.data[3] == math.ceil(length / 7)
                sessions[(src, dst)] = {
                    "len": length,
                    "npk": f.data[3],
                    "next": 1,
                    "window": 0,
                    "data": bytearray(),
                }
            elif kind == 0x11:  # CTS from the receiver (src) for the session dst → src
                s = sessions[(dst, src)]
                assert s["window"] == 0, "CTS while DTs were still owed"
                assert f.data[1] > 0 and f.data[2] == s["next"], f"CTS {f.data.hex()} for {s}"
                assert f.data[3:5] == b"\xff\xff"
                s["window"] = f.data[1]
            elif kind == 0x13:  # EndOfMsgAck from the receiver
                s = sessions.pop((dst, src))
                assert s["next"] == int(s["npk"]) + 1, "ack before every DT came"
                assert f.data[1] | f.data[2] << 8 == s["len"] and f.data[3] == s["npk"]
                data = s["data"]
                assert isinstance(data, bytearray)
                assert all(b == 0xFF for b in data[int(s["len"]) :]), "last DT padded with 0xFF"
                done.append(bytes(data[: int(s["len"])]))
            elif kind == 0xFF:
                sessions.pop((src, dst), None)
                sessions.pop((dst, src), None)
            else:
                raise AssertionError(f"unknown TP.CM control byte {kind:#x}")
        else:  # DT from the sender
            s = sessions[(src, dst)]
            assert int(s["window"]) > 0, "DT outside a CTS window"
            assert f.data[0] == s["next"], f"DT sequence {f.data[0]}, expected {s['next']}"
            s["next"] = int(s["next"]) + 1
            s["window"] = int(s["window"]) - 1
            data = s["data"]
            assert isinstance(data, bytearray)
            data += f.data[1:]
    return done


def dp0_sends(frames: list[WireFrame], abh3: int, start: float, end: float) -> list[float]:
    """When the DP0 commands to drive ``abh3`` (host 2) went on the wire in [start, end]."""
    dp0 = ids.dp0_command_id(abh3, 2)
    return [f.start for f in frames if f.arbitration_id == dp0 and start <= f.start <= end]
