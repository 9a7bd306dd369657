""" "The last frame is the safe word": zero setpoints, every switch off but data select.

One definition for every test: on a simulated drive (what it was last told), in a
recording (a subprocess's wire), or on a decoded command. The wire monitor judges the same
in-process on every bus (``safe_exit``); these are for what it cannot see.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import can

from abh3_supervisor.protocol import flags, frames, ids
from abh3_supervisor.protocol.flags import Layout
from abh3_supervisor.protocol.generation import Generation
from abh3_supervisor.simulator.drive import SimDrive

DEMO_DRIVES = {1: Generation.G2021, 3: Generation.G2023}  # configs/demo.yaml, host 2


def is_safe_word(inputs: int, layout: Layout) -> bool:
    """Nothing set but data select, in the layout's generation."""
    return inputs & ~layout.select_mask == 0


def assert_drive_stopped(drive: SimDrive) -> None:
    """The drive's last command: zero, and nothing set but data select."""
    assert drive.cmd_raw == (0, 0)
    assert is_safe_word(drive.inputs, drive.layout), hex(drive.inputs)


def is_stop(cmd: frames.Dp0Command, layout: Layout) -> bool:
    """A stop command: zero setpoints and the safe word."""
    return (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0) and is_safe_word(cmd.inputs, layout)


def commands_to(
    record: Path, abh3: int, generation: Generation, host: int = 2
) -> list[frames.Dp0Command]:
    """Every DP0 command to drive ``abh3`` in a recording, in order."""
    out = []
    for msg in can.LogReader(str(record)):
        if msg.arbitration_id == ids.dp0_command_id(abh3, host):
            cmd = frames.decode_dp0_command(bytes(msg.data), generation)
            assert isinstance(cmd, frames.Dp0Command)
            out.append(cmd)
    return out


def last_commands(
    record: Path, drives: Mapping[int, Generation], host: int = 2
) -> dict[int, frames.Dp0Command]:
    """The last DP0 command to each drive (address → generation) in a recording."""
    sent = {abh3: commands_to(record, abh3, gen, host) for abh3, gen in drives.items()}
    return {abh3: cmds[-1] for abh3, cmds in sent.items() if cmds}


def assert_stopped_in(record: Path, drives: Mapping[int, Generation], host: int = 2) -> None:
    """Every drive's last DP0 command in ``record`` is the stop: zero and the safe word."""
    last = last_commands(record, drives, host)
    assert set(last) == set(drives), f"commands to {sorted(last)} only"
    for abh3, cmd in last.items():
        assert (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0), (abh3, cmd)
        assert is_safe_word(cmd.inputs, flags.layout(drives[abh3])), (abh3, hex(cmd.inputs))


def assert_demo_stopped(record: Path) -> None:
    """:func:`assert_stopped_in` for configs/demo.yaml's drives (a 2021 at 1, a 2023 at 3)."""
    assert_stopped_in(record, DEMO_DRIVES)
