"""Recordings on disk between flushes, as a ``kill -9`` leaves them; a recording cut short
by a write error ends the run with exit code 5, the drives stopped as always."""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import time
from pathlib import Path
from typing import Any

import can
import pytest

from abh3_supervisor.clients.decode import read_messages
from abh3_supervisor.config import parse_config
from abh3_supervisor.runtime import recorder
from abh3_supervisor.runtime.headless import run_headless
from abh3_supervisor.runtime.recorder import WholeLines, open_recorder
from abh3_supervisor.runtime.stopping import EXIT_RECORDING_FAILED
from abh3_supervisor.simulator.bus import SimBus
from tests.support.disk import FillsUp
from tests.support.safe_word import assert_drive_stopped

MOVING = """
buses:
  b: {interface: virtual, channel: t, simulate: true}
units:
  - {name: left, abh3_id: 1, command_rate_hz: 50, startup: ["SERVO ON ON", "START ON ON", "VEL 200 0"]}
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor, command_rate_hz: 50,
     startup: ["SERVO ON ON", "START ON ON", "VEL 100 -100"]}
"""
CONFIG = parse_config(MOVING, "moving.yaml")


def frames(n: int, t0: float) -> list[can.Message]:
    return [
        can.Message(
            timestamp=t0 + i / 100,
            arbitration_id=0x0C010200 + i % 5,
            is_extended_id=True,
            is_rx=i % 2 == 1,
            data=bytes([i % 256, 1, 2, 3, 4, 5, 6, 7]),
            channel="t",
        )
        for i in range(n)
    ]


def on_disk(path: Path) -> list[can.Message]:
    return list(read_messages(path, report=lambda text: None))


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".csv", ".mcap"])
def test_after_a_flush_the_file_holds_every_frame_so_far_and_only_whole_ones(
    tmp_path: Path, suffix: str
) -> None:
    if suffix == ".mcap":
        pytest.importorskip("mcap_ros2")
    path = tmp_path / f"run{suffix}"
    rec = open_recorder(path, CONFIG)
    t0 = time.time() // 1 + 0.024  # 24 ms: python-can's .asc header wrote ".24" (240 ms)
    first, then = frames(300, t0), frames(40, t0 + 3)
    try:
        for msg in first:
            rec.on_message_received(msg)
        rec.flush()
        for msg in then:  # not flushed: a kill now loses these, and only these
            rec.on_message_received(msg)
        kept = on_disk(path)  # the writer never stopped, as after a kill -9
    finally:
        rec.stop()
    assert [(m.arbitration_id, bytes(m.data)) for m in kept] == [
        (m.arbitration_id, bytes(m.data)) for m in first
    ]
    steps = [b.timestamp - a.timestamp for a, b in itertools.pairwise(kept)]
    assert all(abs(s - 0.01) < 1e-4 for s in steps)
    if suffix == ".asc":  # decoded from its first frame; the header has the wall clock
        kept = list(can.ASCReader(str(path), relative_timestamp=False))[: len(first)]
    assert abs(kept[0].timestamp - t0) < 1e-3  # .blf: its header is up to date
    assert len(on_disk(path)) == len(first) + len(then)  # stop() wrote the rest


def test_a_finished_mcap_recording_indexes_every_chunk(tmp_path: Path) -> None:
    """Chunks closed at every flush, and their index kept on disk, not in memory: the
    summary a seeking reader starts from lists every chunk, and finds every message
    through it; the index's file has no name, so nothing is left beside the recording."""
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    path = tmp_path / "run.mcap"
    rec = open_recorder(path, CONFIG)
    for n in range(5):
        for msg in frames(100, 1000.0 + n):
            rec.on_message_received(msg)
        rec.flush()
    index = getattr(rec.writer, "index", None)
    assert index is not None and index.count == 5 and index.size > 0  # bytes, on disk
    assert os.fstat(index.file.fileno()).st_nlink == 0  # unlinked: gone however it ends
    rec.stop()
    assert index.file.closed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]
    with path.open("rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        assert [c.message_start_time for c in summary.chunk_indexes] == [
            c.message_start_time for c in chunks
        ]
        assert len(chunks) == 5
        assert sum(1 for _ in reader.iter_messages()) == 500


def test_a_full_disk_under_the_mcap_index_ends_the_recording_keeping_its_chunks(
    tmp_path: Path,
) -> None:
    """The index file beside the recording fills the disk too: the recording ends once,
    as for its own file, and the chunks already written read back."""
    pytest.importorskip("mcap_ros2")
    path = tmp_path / "run.mcap"
    rec = open_recorder(path, CONFIG)
    index = rec.writer.index  # type: ignore[attr-defined]
    for msg in frames(100, 1000.0):
        rec.on_message_received(msg)
    rec.flush()
    index.file = FillsUp(index.file, room=0)
    for msg in frames(100, 1001.0):
        rec.on_message_received(msg)
    rec.flush()  # closes a chunk: its index record meets the full disk
    assert rec.failed is not None and "No space left" in rec.failed
    for msg in frames(100, 1002.0):
        rec.on_message_received(msg)  # ignored from now on: no second error
    rec.stop()
    assert len(on_disk(path)) >= 100


@pytest.mark.wallclock
def test_a_full_disk_ends_the_recording_and_the_run_says_so_with_the_drives_stopped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    class FullDisk(WholeLines):
        def __init__(self, path: Path) -> None:
            super().__init__(path)
            self._file = FillsUp(self._file, room=20_000)  # type: ignore[assignment]

    monkeypatch.setattr(recorder, "WholeLines", FullDisk)
    sims: list[SimBus] = []
    made = SimBus.for_units

    def for_units(*args: Any, **kwargs: Any) -> SimBus:
        sims.append(made(*args, **kwargs))
        return sims[-1]

    monkeypatch.setattr(SimBus, "for_units", for_units)
    path = tmp_path / "full.log"
    with caplog.at_level(logging.INFO):
        code = asyncio.run(run_headless(CONFIG, duration=2.0, record=path, status_interval=0))
    assert code == EXIT_RECORDING_FAILED
    # the drives moved, and were stopped as on any way out
    drives = list(sims[0].drives.values())
    assert all(d.pulses != [0.0, 0.0] for d in drives)  # they turned before the stop
    for drive in drives:
        assert_drive_stopped(drive)
        assert not drive.control_word() & (drive.layout.servo.both | drive.layout.start.both)
    assert caplog.text.count("stop frame confirmed by the drive") == 2
    # what is on disk: whole lines, every one a frame
    text = path.read_text(encoding="utf-8")
    assert text and text.endswith("\n") and len(text.encode()) <= 20_000
    assert len(on_disk(path)) == text.count("\n")
    # the stop report says what stopped early, when, and the exit code
    assert caplog.text.count("the recording ends here") == 1
    assert f"recording {path.resolve()} stopped early, at " in caplog.text
    assert "No space left on device" in caplog.text
    assert f"stopped early on a write error (the disk full?): --record {path}" in caplog.text
    assert "(exit code 5)" in caplog.text
    assert "Traceback" not in caplog.text
