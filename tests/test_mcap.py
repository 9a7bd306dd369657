"""``--record run.mcap``: raw frames and decoded values as ROS 2 messages, read back by
independent readers (the mcap library's and rosbags'), with counts that match the frames.

The demo's two simulated drives (2021 and 2023) run headless in-process for two seconds.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.clients.decode import decode_file
from abh3_supervisor.config import Config, parse_config
from abh3_supervisor.runtime.headless import run_headless
from abh3_supervisor.runtime.mcap_recording import McapRecording, read_frames
from abh3_supervisor.runtime.recorder import GuardedRecorder
from abh3_supervisor.runtime.ros_topics import VENDOR

pytest.importorskip("mcap_ros2")
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from tests.support.disk import FillsUp

ROOT = Path(__file__).resolve().parent.parent
CONFIG = """
buses:
  demo: {interface: virtual, channel: mcap-test, simulate: true}
units:
  - name: left
    abh3_id: 1
    broadcast: {mask: 0x7f, rate_hz: 14}
    geometry: {pulses_per_rev: 4096}
    startup: ["SERVO ON ON", "START ON ON", "VEL 300 20"]
  - {name: right, abh3_id: 3, protocol: "2023", velocity_model: motor,
     broadcast: {mask: 0x0f, rate_hz: 8}}
"""


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Config, int, int]:
    """A two-second run recorded to MCAP: the file, its config, frames sent and received."""
    path = tmp_path_factory.mktemp("mcap") / "run.mcap"
    config = parse_config(CONFIG, "mcap.yaml")
    handler, root = Collect(), logging.getLogger()
    level = root.level
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        code = asyncio.run(run_headless(config, duration=2.0, record=path, status_interval=0))
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
    assert code == 0
    found = [
        re.search(r"recorded \d+ frames \((\d+) sent, (\d+) received\)", m) for m in handler.lines
    ]
    sent, received = next((int(m[1]), int(m[2])) for m in found if m)
    return path, config, sent, received


class Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def counts(path: Path) -> dict[str, int]:
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    by_id = summary.statistics.channel_message_counts
    return {c.topic: by_id.get(i, 0) for i, c in summary.channels.items()}


@pytest.mark.wallclock
def test_raw_frames_are_every_frame_the_pumps_sent_and_received(
    recording: tuple[Path, Config, int, int],
) -> None:
    path, _, sent, received = recording
    topics = counts(path)
    assert topics["/can/demo/tx"] == sent > 150
    assert topics["/can/demo/rx"] == received > 150


@pytest.mark.wallclock
def test_decoded_values_match_the_frames_they_came_from(
    recording: tuple[Path, Config, int, int],
) -> None:
    """One vel_fbk_ab/_yx per DP0 reply, one brd<n>_data per broadcast n, an odom per DP0
    reply of the unit with pulses_per_rev (a one-drive robot: each reply is a round of its
    feedback, issue 51): counted from the raw frames in the file."""
    path, config, _, _ = recording
    frames: collections.Counter[str] = collections.Counter()
    for line in decode_file(path, config, as_json=True):
        rec = json.loads(line)
        if rec["kind"] == "dp0_reply":
            frames[f"/{rec['unit']}/vel_fbk_ab"] += 1
            frames[f"/{rec['unit']}/vel_fbk_yx"] += 1
            if rec["unit"] == "left":
                frames["/left/odom"] += 1
        elif rec["kind"] == "broadcast" and rec["packet"] < 7:
            frames[f"/{rec['unit']}/brd{rec['packet']}_data"] += 1
    topics = counts(path)
    decoded = {t: n for t, n in topics.items() if not t.startswith(("/can/", "/diagnostics"))}
    assert decoded == dict(frames)
    assert {t for t in decoded if "right" in t} == {
        "/right/vel_fbk_ab", "/right/vel_fbk_yx", *(f"/right/brd{n}_data" for n in range(4))
    }  # fmt: skip
    assert 2 <= topics["/diagnostics"] <= 6  # once a second and on changes


@pytest.mark.wallclock
def test_rosbags_reads_every_message_with_the_files_own_schemas(
    recording: tuple[Path, Config, int, int],
) -> None:
    from rosbags.highlevel import AnyReader

    path, _, sent, _ = recording
    seen: collections.Counter[str] = collections.Counter()
    last: dict[str, Any] = {}
    with AnyReader([path]) as reader:
        assert {c.msgtype for c in reader.connections} == {
            "can_msgs/msg/Frame",
            "diagnostic_msgs/msg/DiagnosticArray",
            "nav_msgs/msg/Odometry",
            *(f"abh3_can_interface/msg/{name}" for name in VENDOR),
        }
        reached = False
        for connection, _, raw in reader.messages():
            last[connection.topic] = reader.deserialize(raw, connection.msgtype)
            seen[connection.topic] += 1
            if connection.topic == "/left/vel_fbk_yx":
                fbk = last[connection.topic]
                reached |= (fbk.vel_ay, fbk.vel_bx) == (300.0, 20.0)
    assert dict(seen) == counts(path)
    assert seen["/can/demo/tx"] == sent
    assert reached  # the startup's VEL 300 20 (the way out then ramps it down to standing)
    assert last["/left/odom"].pose.pose.position.x > 0
    assert last["/left/odom"].child_frame_id == "base_link"
    diag = {s.name: s for s in last["/diagnostics"].status}
    assert set(diag) == {
        "abh3_supervisor: bus demo",
        "abh3_supervisor: unit left",
        "abh3_supervisor: unit right",
        "abh3_supervisor: robot left",  # the robot decision: one status per robot
        "abh3_supervisor: robot right",
    }
    assert diag["abh3_supervisor: unit left"].level == 0
    frame = last["/can/demo/tx"]
    assert frame.is_extended and frame.dlc in (3, 8) and frame.header.frame_id == "demo"


@pytest.mark.wallclock
def test_the_mcap_library_decodes_it_as_ros2_and_the_file_is_indexed(
    recording: tuple[Path, Config, int, int],
) -> None:
    path = recording[0]
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        messages = list(reader.iter_decoded_messages(topics=["/left/brd5_data"]))
    assert messages and all(m.decoded_message.main_volt > 0 for m in messages)


def test_the_vendor_schemas_are_the_shipped_interface_files() -> None:
    folder = ROOT / "plugins/abh3_plugins/ros2/interface/abh3_can_interface/msg"
    for name, text in VENDOR.items():
        shipped = [
            line.split("#")[0].strip() for line in (folder / f"{name}.msg").read_text().splitlines()
        ]
        assert [line for line in shipped if line] == text.splitlines(), name


@pytest.mark.wallclock
def test_abh3_decode_reads_it_as_it_reads_a_can_log(
    recording: tuple[Path, Config, int, int], capsys: pytest.CaptureFixture[str]
) -> None:
    path, _, sent, received = recording
    assert main(["decode", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == sent + received
    assert sum(" → id1 " in line and "dp0_command" in line for line in lines) > 50


def test_a_file_that_breaks_off_reads_up_to_where_it_does(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A crash leaves the chunks written so far and no index: read as a stream."""
    import can

    from abh3_supervisor.runtime import mcap_recording

    monkeypatch.setattr(mcap_recording, "CHUNK_BYTES", 4096)  # many chunks in a small file
    path = tmp_path / "whole.mcap"
    rec = mcap_recording.open_mcap(path, parse_config(CONFIG, "mcap.yaml"))
    for i in range(5000):
        rec.on_message_received(
            can.Message(arbitration_id=i, data=bytes(8), channel="mcap-test", timestamp=i / 1000)
        )
    rec.stop()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    said: list[str] = []
    frames = list(_drain(read_frames(cut, said.append)))
    assert 1000 < len(frames) < 5000
    assert [f.arbitration_id for f in frames] == list(range(len(frames)))
    assert said and "breaks off" in said[-1]


def _drain(gen: Any) -> Any:
    result = yield from gen
    return result


def test_a_full_disk_ends_the_recording_once_and_keeps_what_was_written(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    import can

    path = tmp_path / "full.mcap"
    config = parse_config(CONFIG, "mcap.yaml")
    real = path.open("wb")
    full: Any = FillsUp(real, 300_000)
    guarded = GuardedRecorder(path, McapRecording(full, config))
    data = bytes(range(8))
    for i in range(40_000):  # ~1 MB of frames: the disk fills part-way
        guarded.on_message_received(
            can.Message(arbitration_id=i, data=data, channel="mcap-test", timestamp=i / 1000)
        )
    guarded.stop()  # no exception, no second error
    real.close()
    assert guarded.failed is not None and "No space left" in guarded.failed
    assert caplog.text.count("the recording ends here") == 1
    said: list[str] = []
    kept = list(_drain(read_frames(path, said.append)))
    assert len(kept) > 1000  # the whole chunks before the disk filled
    assert [m.arbitration_id for m in kept] == list(range(len(kept)))


@pytest.mark.wallclock
def test_without_the_mcap_extra_the_run_says_how_to_get_it_before_any_drive_moves(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    for name in [n for n in sys.modules if n.split(".")[0] in ("mcap", "mcap_ros2")]:
        monkeypatch.setitem(sys.modules, name, None)  # an import fails as if absent
    monkeypatch.setitem(sys.modules, "mcap", None)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG)
    out = tmp_path / "run.mcap"
    code = main(
        ["run", str(cfg), "--headless", "--duration", "1", "--record", str(out), "--no-socket"]
    )
    err = capsys.readouterr().err
    assert code == 1
    assert "pip install 'abh3-supervisor[mcap]'" in err
    assert not out.exists()
    assert "startup" not in caplog.text  # nothing was commanded


@pytest.mark.wallclock
def test_without_mcap_the_recording_module_imports_and_says_what_to_install() -> None:
    """A process with no mcap at all: the module imports (decode and the recorder import
    it lazily, then ask it), and opening a recording says what to install."""
    code = (
        "import sys\n"
        "sys.modules['mcap'] = sys.modules['mcap_ros2'] = None\n"
        "from pathlib import Path\n"
        "from abh3_supervisor.config import parse_config\n"
        "from abh3_supervisor.errors import BusOpenError\n"
        "from abh3_supervisor.runtime.mcap_recording import open_mcap\n"
        f"config = parse_config({CONFIG!r}, 'c.yaml')\n"
        "try:\n"
        "    open_mcap(Path('never.mcap'), config)\n"
        "except BusOpenError as exc:\n"
        "    print(exc)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "pip install 'abh3-supervisor[mcap]'" in out.stdout


@pytest.mark.wallclock
def test_the_core_loads_mcap_only_for_an_mcap_recording() -> None:
    code = (
        "import sys, abh3_supervisor.runtime.bus_runtime, abh3_supervisor.runtime.headless, "
        "abh3_supervisor.clients.cli, abh3_supervisor.clients.decode\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('mcap', 'mcap_ros2'))\n"
        "print(bad); sys.exit(bool(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


EIGHT = (
    "buses:\n  b: {interface: virtual, channel: mcap-kill, bitrate: 1000000, simulate: true}\nunits:\n"
    + "".join(f"  - {{name: u{i}, abh3_id: {i + 1}, host_id: 100}}\n" for i in range(8))
)


@pytest.mark.wallclock
def test_kill_9_keeps_every_chunk_written_before_it(tmp_path: Path) -> None:
    """A real crash: `abh3 run` killed with SIGKILL mid-run. The file has no index; the
    frames of every chunk written before the kill read back."""
    cfg = tmp_path / "eight.yaml"
    cfg.write_text(EIGHT)
    out = tmp_path / "killed.mcap"
    command = [sys.executable, "-m", "abh3_supervisor", "run", str(cfg), "--headless"]
    proc = subprocess.Popen(
        [
            *command,
            "--record",
            str(out),
            "--no-socket",
            "--status-interval",
            "1",
            "--duration",
            "30",
        ],
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    assert proc.stderr is not None
    reports = 0
    for line in proc.stderr:  # one status line per unit each second: wait for 5 s of them
        reports += " b/u0: " in line
        if reports >= 5:
            break
    proc.kill()
    proc.wait(timeout=10)
    said: list[str] = []
    frames = list(_drain(read_frames(out, said.append)))
    assert len(frames) > 2000  # ≈ 960 frames/s: at least two seconds' worth of chunks
    stamps = [f.timestamp for f in frames]
    assert max(stamps) - min(stamps) >= 2.0
    assert {f.is_rx for f in frames} == {True, False}
    assert said and "breaks off" in said[-1]
