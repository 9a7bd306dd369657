""" "The last frame is the safe word", judged from a recording (a subprocess's wire)."""

from __future__ import annotations

from pathlib import Path

import can


def assert_demo_stopped(record: Path) -> None:
    """The last DP0 command to each of configs/demo.yaml's drives (a 2021 at 1, a 2023 at
    3, host 2) in a ``--record`` file is the stop: zero and the safe word."""
    from abh3_supervisor.protocol import flags, frames, ids

    layouts = {1: flags.LAYOUT_2021, 3: flags.LAYOUT_2023}
    last = {}
    for msg in can.LogReader(str(record)):
        for abh3, lay in layouts.items():
            if msg.arbitration_id == ids.dp0_command_id(abh3, 2):
                last[abh3] = frames.decode_dp0_command(bytes(msg.data), lay.generation)
    assert len(last) == 2
    for abh3, cmd in last.items():
        assert isinstance(cmd, frames.Dp0Command) and (cmd.cmd_ay, cmd.cmd_bx) == (0.0, 0.0)
        assert cmd.inputs & ~layouts[abh3].select_mask == 0  # the safe word
