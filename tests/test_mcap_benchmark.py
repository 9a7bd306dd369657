"""Section 11 of the benchmarks (benchmarks/recording.py) runs and gives sane figures: the
loop's CPU for a `.log` and an `.mcap` run, the recorder's share of it, the encoders'
times. No timed assertions."""

from __future__ import annotations

import pytest

from benchmarks import recording


@pytest.mark.wallclock
def test_the_recording_section_runs_one_interleaved_pair() -> None:
    pytest.importorskip("mcap_ros2")
    rows = {row.figure.split(":")[0]: row for row in recording.rows(0.5, 1)}
    loop = rows["loop thread CPU, % of one core"]
    share = rows["the recorder's own share of the loop"]
    frames = rows["frames on the bus (every one recorded)"]
    assert frames.baseline is not None and frames.ours > 100 and frames.baseline > 100
    assert rows["loop thread CPU per frame"].ours > 0
    for row in (loop, share):
        assert row.baseline is not None and 0 < row.baseline < 100 and 0 < row.ours < 100
    assert loop.baseline is not None and share.baseline is not None
    assert share.ours < loop.ours and share.baseline < loop.baseline  # a part of it
    encode = rows["encode a can_msgs/Frame"]
    assert encode.baseline is not None and 0 < encode.ours < encode.baseline
