"""``--foxglove [HOST:]PORT``: the recording's topics live over the Foxglove WebSocket
protocol, read by a real WebSocket client (the ``websockets`` package) and decoded with
mcap_ros2's decoder from the schemas the server advertises; a viewer that never reads
leaves the drives' exchanges alone while its own queue drops what it cannot take
(counted per viewer: tests/test_watchers_foxglove.py).

Everything binds to 127.0.0.1, on a port the system picks (``:0``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, ClassVar, TypeVar, cast

import pytest

from abh3_supervisor.clients.cli import main
from abh3_supervisor.config import Config
from abh3_supervisor.config.endpoint import Endpoint, parse_endpoint
from abh3_supervisor.errors import ConfigError
from abh3_supervisor.runtime import foxglove_live, foxglove_server
from abh3_supervisor.runtime.bus_runtime import Runtime
from abh3_supervisor.runtime.foxglove_live import SUBPROTOCOL

pytest.importorskip("websockets")
pytest.importorskip("mcap_ros2")
import websockets
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from websockets.typing import Subprotocol

from tests.support.foxglove import CONFIG, config

T = TypeVar("T")
ROOT = Path(__file__).resolve().parent.parent
MESSAGE_DATA = 0x01  # the protocol's binary opcode: subscription id, log time, payload
WAIT_S = 10.0  # a condition not met by then is a failure, not a slow machine


async def serving(cfg: Config, viewer: Callable[[Runtime, int], Awaitable[T]]) -> T:
    """Run ``cfg`` on the simulator while ``viewer`` watches its Foxglove port."""
    async with Runtime(cfg, foxglove=cfg.foxglove) as rt:
        assert rt.foxglove is not None
        stop = asyncio.Event()
        running = asyncio.ensure_future(rt.run_until(stop))
        try:
            return await viewer(rt, rt.foxglove.port)
        finally:
            stop.set()
            await running


class Viewer:
    """A Foxglove WebSocket client: the channels advertised, subscriptions, decoding."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}  # topic → the advertised channel
        self.info: dict[str, Any] = {}
        self.by_subscription: dict[int, dict[str, Any]] = {}
        self._decoders = DecoderFactory()

    async def next(self) -> Any:
        """The next message; JSON ones update what is known."""
        raw = await asyncio.wait_for(self.ws.recv(), WAIT_S)
        if isinstance(raw, str):
            message = json.loads(raw)
            if message["op"] == "serverInfo":
                self.info = message
            elif message["op"] == "advertise":
                self.channels.update((c["topic"], c) for c in message["channels"])
            return message
        return raw

    async def until_advertised(self, *topics: str) -> None:
        while not set(topics) <= set(self.channels):
            await self.next()

    async def subscribe(self, *topics: str) -> None:
        await self.until_advertised(*topics)
        subscriptions = []
        for topic in topics:
            sub = len(self.by_subscription) + 1
            self.by_subscription[sub] = self.channels[topic]
            subscriptions.append({"id": sub, "channelId": self.channels[topic]["id"]})
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def decode(self, raw: bytes) -> tuple[str, int, Any]:
        """A binary message's topic, log time and the ROS 2 message, decoded with
        mcap_ros2 from the schema the server advertised for its channel."""
        assert raw[0] == MESSAGE_DATA
        sub, ns = struct.unpack_from("<IQ", raw, 1)
        channel = self.by_subscription[sub]
        assert (channel["encoding"], channel["schemaEncoding"]) == ("cdr", "ros2msg")
        schema = Schema(
            id=channel["id"],
            name=channel["schemaName"],
            encoding="ros2msg",
            data=channel["schema"].encode(),
        )
        decoder = self._decoders.decoder_for("cdr", schema)
        assert decoder is not None
        return channel["topic"], ns, decoder(raw[13:])

    async def until(self, check: Callable[[str, Any], bool]) -> tuple[str, Any]:
        while True:
            raw = await self.next()
            if isinstance(raw, bytes):
                topic, _, message = self.decode(raw)
                if check(topic, message):
                    return topic, message


def connect(port: int, **options: Any) -> Any:
    return websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol(SUBPROTOCOL)], **options
    )


# ------------------------------------------------------------------ a viewer decodes


@pytest.mark.wallclock
def test_a_viewer_decodes_the_units_feedback_frames_and_diagnostics() -> None:
    async def watch(rt: Runtime, port: int) -> dict[str, Any]:
        async with connect(port) as ws:
            view = Viewer(ws)
            await view.next()
            assert view.info["op"] == "serverInfo"
            assert view.info["capabilities"] == []  # watch only: nothing a viewer can send
            await view.subscribe("/left/vel_fbk_ab", "/can/demo/tx", "/diagnostics")
            seen: dict[str, Any] = {}

            def check(topic: str, message: Any) -> bool:
                unit = topic == "/left/vel_fbk_ab"
                if not unit or (message.vel_ay, message.vel_bx) == (120.0, -80.0):
                    seen[topic] = message
                return len(seen) == 3

            await view.until(check)
            return seen

    seen = asyncio.run(serving(config(), watch))
    # the unit's velocity feedback once the simulated drive reached its command
    assert (seen["/left/vel_fbk_ab"].vel_ay, seen["/left/vel_fbk_ab"].vel_bx) == (120.0, -80.0)
    frame = seen["/can/demo/tx"]
    assert frame.header.frame_id == "demo" and frame.dlc in (3, 8) and frame.is_extended
    names = {status.name for status in seen["/diagnostics"].status}
    assert any("left" in name for name in names), names


@pytest.mark.wallclock
def test_every_topic_of_the_recording_is_advertised_with_its_schema() -> None:
    async def watch(rt: Runtime, port: int) -> dict[str, dict[str, Any]]:
        async with connect(port) as ws:
            view = Viewer(ws)
            wanted = [
                "/can/demo/tx",
                "/can/demo/rx",
                "/left/vel_fbk_ab",
                "/left/vel_fbk_yx",
                *(f"/left/brd{n}_data" for n in range(7)),
                *(f"/right/brd{n}_data" for n in range(4)),
                "/left/odom",
                "/diagnostics",
            ]
            await view.until_advertised(*wanted)
            return view.channels

    channels = asyncio.run(serving(config(), watch))
    assert channels["/left/odom"]["schemaName"] == "nav_msgs/msg/Odometry"
    assert channels["/can/demo/rx"]["schemaName"] == "can_msgs/msg/Frame"
    assert channels["/left/brd2_data"]["schemaName"] == "abh3_can_interface/msg/Abh3Brd2"
    assert {c["encoding"] for c in channels.values()} == {"cdr"}
    assert {c["schemaEncoding"] for c in channels.values()} == {"ros2msg"}


# ------------------------------------------------------------------ a viewer that never reads


@pytest.mark.wallclock
def test_a_viewer_that_never_reads_costs_the_bus_nothing() -> None:
    """It subscribes to everything, then reads nothing while the drives run at 100 Hz:
    a write on the bus loop stays a few microseconds (it never does a viewer's work,
    never waits for the viewer), every unit keeps its rate and no exchange times out."""
    run_s = 4.0

    async def stall(rt: Runtime, port: int) -> tuple[int, int, list[int], dict[str, Any]]:
        assert rt.foxglove is not None
        sink = rt.foxglove.sink
        spent: list[int] = []  # ns in each write, on the bus loop
        write, feeding = sink.write, [True]

        def timed(topic: str, schema: str, data: bytes, ns: int) -> None:
            if not feeding[0]:
                return
            start = time.perf_counter_ns()
            write(topic, schema, data, ns)
            spent.append(time.perf_counter_ns() - start)

        sink.write = timed  # type: ignore[method-assign]
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # fills at once
        sock.connect(("127.0.0.1", port))
        # the client library stops reading at 1 message queued: the socket fills up
        async with connect(port, sock=sock, max_queue=1) as ws:
            view = Viewer(ws)
            await view.until_advertised("/can/demo/tx", "/can/demo/rx", "/left/vel_fbk_ab")
            await view.subscribe(*view.channels)
            served_before, spent[:] = sink.served, []
            await rt.run_until(asyncio.Event(), timeout=run_s)  # the drives run; no read
            now = asyncio.get_running_loop().time()
            timing = {
                unit: (slot.stats.achieved_rate_hz(now), slot.stats.timeouts)
                for scheduler in rt.supervisor.schedulers.values()
                for unit, slot in scheduler.slots.items()
            }
            feeding[0] = False  # what the viewer gets from here on was served before
            await asyncio.wait_for(_drained(sink), WAIT_S)
            served = sink.served - served_before
            received = 0
            try:  # what reached the viewer, read now
                while True:
                    raw = await asyncio.wait_for(ws.recv(), 0.5)
                    received += isinstance(raw, bytes)
            except TimeoutError:
                pass
            return served, received, spent, timing

    served, received, spent, timing = asyncio.run(serving(config(), stall))
    for unit, (rate, timeouts) in timing.items():
        assert timeouts == 0, unit
        assert rate == pytest.approx(100.0, rel=0.05), unit  # 5 %: a shared machine's noise
    spent.sort()
    assert spent[len(spent) * 99 // 100] < 100_000, "a write took ≥ 0.1 ms (p99)"
    assert sum(spent) < 0.01 * run_s * 1e9, "writes took ≥ 1 % of the run"
    assert served > 1000  # what it subscribed to went on being served…
    assert received <= served  # …and reached it as far as its socket took them


@pytest.mark.wallclock
def test_a_starved_drain_drops_counts_and_says_so_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The server's thread, which takes the queued messages, gets no CPU (held here):
    the queue stops at its bound, every message past it is dropped and counted, the log
    says so once, and the drives run on."""
    monkeypatch.setattr(foxglove_live, "QUEUE", 200)
    held = threading.Event()

    async def starve(rt: Runtime, port: int) -> tuple[int, int, int]:
        assert rt.foxglove is not None
        sink = rt.foxglove.sink
        sink.drain = held.wait  # type: ignore[method-assign,assignment]
        rt.foxglove.watchers.subscriptions.add((1, 1))  # a viewer: the topics are produced
        await rt.run_until(asyncio.Event(), timeout=1.5)
        timeouts = sum(
            slot.stats.timeouts
            for scheduler in rt.supervisor.schedulers.values()
            for slot in scheduler.slots.values()
        )
        held.set()
        return len(sink.queue), sink.dropped, timeouts

    with caplog.at_level(logging.INFO):
        queued, dropped, timeouts = asyncio.run(serving(config(), starve))
    assert queued == 200 and dropped > 500 and timeouts == 0
    said = [r.getMessage() for r in caplog.records if "falls behind" in r.getMessage()]
    assert len(said) == 1
    at_end = re.search(
        r"foxglove: stopped; \d+ message\(s\) handed to the server for its viewers, (\d+) dropped",
        caplog.text,
    )
    assert at_end is not None and int(at_end[1]) >= dropped  # the stop frames' too


async def _drained(sink: Any) -> None:
    """Until the server's thread has taken everything queued."""
    while sink.queue:
        await asyncio.sleep(0.01)  # polls a condition; the drain runs on its own thread


# ------------------------------------------------------------------ with a recording


@pytest.mark.wallclock
def test_with_an_mcap_recording_both_get_the_same_messages(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"

    async def watch(rt: Runtime, port: int) -> int:
        async with connect(port) as ws:
            view = Viewer(ws)
            await view.subscribe("/left/vel_fbk_ab")
            await view.until(lambda topic, m: m.vel_ay == 120.0)
            return 1

    async def run() -> int:
        cfg = config()
        async with Runtime(cfg, record=path, foxglove=cfg.foxglove) as rt:
            assert rt.foxglove is not None
            stop = asyncio.Event()
            running = asyncio.ensure_future(rt.run_until(stop))
            try:
                return await watch(rt, rt.foxglove.port)
            finally:
                stop.set()
                await running

    assert asyncio.run(run()) == 1
    from mcap.reader import make_reader

    with path.open("rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}  # type: ignore[union-attr]
    assert "/left/vel_fbk_ab" in topics and "/can/demo/tx" in topics


@pytest.mark.wallclock
def test_while_nobody_watches_the_frames_and_feedback_are_not_even_produced() -> None:
    """No viewer: the producer sees each bus direction's first frame only (its channel is
    made, for a viewer to find), not the hundreds after it; then a viewer subscribes and
    they flow (the first test above decodes them)."""

    async def idle(rt: Runtime, port: int) -> tuple[int, int, dict[str, Any]]:
        feed = rt.pumps["demo"].recorder
        assert isinstance(feed, foxglove_live.LiveFeed)
        produced, frames = [0], [0]
        make = feed.topics.on_message_received

        def counted(msg: Any) -> None:
            produced[0] += 1
            make(msg)

        feed.topics.on_message_received = counted  # type: ignore[method-assign]
        seen = feed.on_message_received

        def every(msg: Any) -> None:
            frames[0] += 1
            seen(msg)

        feed.on_message_received = every  # type: ignore[method-assign]  # the pump's call
        await rt.run_until(asyncio.Event(), timeout=1.0)
        unwatched = produced[0], frames[0]
        async with connect(port) as ws:
            view = Viewer(ws)
            await view.subscribe("/can/demo/rx")
            await view.until(lambda topic, m: topic == "/can/demo/rx")
        return unwatched[0], unwatched[1], view.channels

    produced, frames, channels = asyncio.run(serving(config(), idle))
    assert frames > 300 and produced <= 2  # tx and rx made their channels, no more
    assert {"/can/demo/tx", "/can/demo/rx", "/left/vel_fbk_ab"} <= set(channels)


def test_a_full_disk_ends_the_recording_not_the_live_view(tmp_path: Path) -> None:
    """Sharing an .mcap recording's topics, the live view gets every frame once, before
    and after the recording's disk fills (the frames then come to it directly)."""
    import can

    from abh3_supervisor.runtime.mcap_recording import McapRecording
    from abh3_supervisor.runtime.recorder import GuardedRecorder
    from tests.support.disk import FillsUp

    class Seen:
        def __init__(self) -> None:
            self.topics: list[str] = []

        def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
            self.topics.append(topic)

    path = tmp_path / "full.mcap"
    with path.open("wb") as real:
        full: Any = FillsUp(real, 100_000)
        recorder = GuardedRecorder(path, McapRecording(full, config()))
        seen = Seen()
        feed = foxglove_live.live_feed(seen, recorder, config())
        assert feed.shared
        frames = 20_000  # ~0.5 MB recorded: the disk fills part-way
        for i in range(frames):
            msg = can.Message(arbitration_id=i, data=bytes(8), channel="foxglove-test")
            feed.on_message_received(msg)
        recorder.stop()
    assert recorder.failed is not None and "No space left" in recorder.failed
    assert seen.topics == ["/can/demo/rx"] * frames  # each once, none lost


@pytest.mark.wallclock
def test_a_recording_that_failed_is_said_so_with_a_live_view_too(tmp_path: Path) -> None:
    """The pumps hand their frames to the live feed, the recording behind it: the run's
    end still finds the recording and its failure (exit 5, "stopped early")."""
    from abh3_supervisor.runtime.recording import recorded, write_failures

    path = tmp_path / "run.mcap"

    async def fail_the_disk(rt: Runtime, port: int) -> None:
        assert rt.recording is not None and rt.recording is not rt.pumps["demo"].recorder
        rt.recording.failed = "[Errno 28] No space left on device"

    async def run() -> Runtime:
        async with Runtime(config(), record=path, foxglove=config().foxglove) as rt:
            assert rt.foxglove is not None
            await fail_the_disk(rt, rt.foxglove.port)
        return rt

    rt = asyncio.run(run())
    assert write_failures(rt, None) == [f"--record {path}"]
    assert "stopped early" in recorded(rt, path)


# ------------------------------------------------------------------ the option and the key


def test_an_endpoint_is_loopback_unless_a_host_is_given() -> None:
    assert parse_endpoint(8765) == Endpoint("127.0.0.1", 8765)
    assert parse_endpoint("8765").loopback
    assert parse_endpoint("0.0.0.0:9000") == Endpoint("0.0.0.0", 9000)
    assert str(parse_endpoint("[::1]:9000")) == "[::1]:9000"
    for wrong in ("", "x:", "host:port", "70000", "a b:1", True, 1.5, "١٢٣٤"):
        with pytest.raises(ValueError):
            parse_endpoint(wrong)
    assert parse_endpoint("127.0.0.2:1").loopback and parse_endpoint("[::1]:1").loopback
    assert parse_endpoint("localhost:1").loopback
    assert not parse_endpoint("127.evil.example:1").loopback  # a name, whatever it starts with
    assert not parse_endpoint("0.0.0.0:1").loopback


def test_a_viewers_lines_are_printable_warnings_at_most_and_few(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A viewer's text is in some of the lines its doing adds to the log (ours, and the
    websockets library's): no forged line, no terminal escape, no ERROR of ours, and no
    flood of the log."""
    now = [0.0]
    lines = foxglove_server.ViewerLines(clock=lambda: now[0])
    library = logging.getLogger("websockets.test")

    def said(text: str) -> None:
        record = library.makeRecord(library.name, logging.ERROR, __file__, 1, text, (), None)
        foxglove_server._LibraryLines(lines).handle(record)

    with caplog.at_level(logging.INFO, logger=foxglove_server.log.name):
        said("Invalid message: unknown variant `x\n10:00:00.000 ERROR   unit left: FORGED\x1b[2J`")
        for i in range(1000):  # a flood of them, in one instant
            said(f"Invalid message {i}")
        now[0] += 1.0
        said("a viewer left")
    records = [r for r in caplog.records if r.name == foxglove_server.log.name]
    assert len(records) == foxglove_server.LINES_PER_S + 1
    assert all(r.levelno == logging.WARNING for r in records)
    first = records[0].getMessage()
    assert first.startswith("foxglove: Invalid message") and "\n" not in first
    assert "\x1b" not in first and "FORGED?[2J" in first
    assert records[-1].getMessage() == "foxglove: a viewer left (996 more not shown)"


def test_a_server_that_does_not_end_never_holds_the_way_out(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The way out gives the server's thread a bound, then goes on (a real viewer that
    never reads is cut at the stop: tests/test_watchers_foxglove.py)."""
    released = threading.Event()

    class Stuck:
        port = 1
        watchers = foxglove_live.Watchers()
        viewers: ClassVar = {"#1 127.0.0.1:9": (5, 7)}

        def stop(self, timeout: float) -> bool:
            return released.wait(0)  # its loop held: not ended in time

    sink = foxglove_live.FoxgloveSink({}, lambda *message: None)
    live = foxglove_live.FoxgloveLive(cast(Any, Stuck()), sink, Endpoint("127.0.0.1", 1))
    try:
        with caplog.at_level(logging.WARNING):
            live.stop()  # returns: the way out goes on
        assert "a viewer does not let go" in caplog.text
        assert "viewer #1 127.0.0.1:9 missed 7 of 12 message(s)" in caplog.text
    finally:
        released.set()


def _this_hosts_address() -> str | None:
    """An address of this machine that is not loopback (none: no network at all)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1: nothing is sent, a route is chosen
        except OSError:
            return None
        address = str(probe.getsockname()[0])
    return None if address.startswith("127.") else address


@pytest.mark.wallclock
def test_by_default_it_is_reachable_on_loopback_only() -> None:
    address = _this_hosts_address()
    if address is None:
        pytest.skip("no address but loopback on this machine")

    async def reach(rt: Runtime, port: int) -> None:
        assert rt.foxglove is not None and rt.foxglove.url.startswith("ws://127.0.0.1:")
        async with connect(port) as ws:  # loopback: served
            assert json.loads(await ws.recv())["op"] == "serverInfo"
        with pytest.raises(OSError):  # this machine's own network address: refused
            await asyncio.open_connection(address, port)

    asyncio.run(serving(config(CONFIG.replace("foxglove: 127.0.0.1:0", "foxglove: 0")), reach))


@pytest.mark.wallclock
def test_only_abh3_run_serves_the_files_key_not_the_tools_that_open_its_buses() -> None:
    """`abh3 param -c`, `abh3 check --drives` build their runtime from the same file:
    they serve nothing (nor collide with the port of an `abh3 run`)."""

    async def tool() -> object:
        async with Runtime(config()) as rt:
            return rt.foxglove

    assert asyncio.run(tool()) is None


def test_the_yaml_key_is_checked_with_file_line_and_did_you_mean() -> None:
    assert config().foxglove == Endpoint("127.0.0.1", 0)
    with pytest.raises(ConfigError) as bad:
        config(CONFIG.replace("foxglove: 127.0.0.1:0", "foxglove: 'localhost:99999'"))
    assert "foxglove.yaml:14: foxglove: port 99999 is out of range" in str(bad.value)
    with pytest.raises(ConfigError) as typo:
        config(CONFIG.replace("foxglove:", "foxglov:"))
    assert "unknown key; did you mean 'foxglove'?" in str(typo.value)


def _yaml(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "fg.yaml"
    path.write_text(text)
    return path


@pytest.mark.wallclock
def test_a_port_in_use_is_exit_2_before_any_drive_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    kept = tmp_path / "yesterday.mcap"
    kept.write_bytes(b"yesterday's recording")
    try:
        code = main(
            [
                *("run", str(_yaml(tmp_path, CONFIG)), "--headless", "--no-socket"),
                *("--duration", "5", "--foxglove", str(port), "--record", str(kept)),
            ]
        )
    finally:
        taken.close()
    err = capsys.readouterr().err
    assert code == 2
    assert kept.read_bytes() == b"yesterday's recording"  # refused before it was opened
    assert f"--foxglove 127.0.0.1:{port}: cannot serve: port {port} on 127.0.0.1 is in use" in err


@pytest.mark.wallclock
def test_a_port_in_use_from_the_file_names_its_line_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The endpoint came from the YAML, not the option: the message says where."""
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    path = _yaml(tmp_path, re.sub(r"^foxglove:.*$", f"foxglove: {port}", CONFIG, flags=re.M))
    line = path.read_text().splitlines().index(f"foxglove: {port}") + 1
    try:
        code = main(["run", str(path), "--headless", "--no-socket", "--duration", "5"])
    finally:
        taken.close()
    err = capsys.readouterr().err
    assert code == 2
    assert f"{path}:{line}: foxglove: 127.0.0.1:{port}: cannot serve: port {port}" in err
    assert "give another port (0: any free one" in err and "--foxglove" not in err


def test_a_bad_option_value_is_argparse_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["run", "x.yaml", "--foxglove", "here:there"])
    assert exited.value.code == 2
    assert "argument --foxglove: 'here:there' is not [HOST:]PORT" in capsys.readouterr().err


@pytest.mark.wallclock
def test_without_the_extra_the_run_says_how_to_get_it(tmp_path: Path) -> None:
    """websockets made unimportable in a child: exit 2 and the pip line, nothing started."""
    path = _yaml(tmp_path, CONFIG)
    code = (
        "import sys; sys.modules['websockets'] = None\n"
        "from abh3_supervisor.clients.cli import main\n"
        f"sys.exit(main(['run', {str(path)!r}, '--headless', '--no-socket']))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT
    )
    assert done.returncode == 2, done.stderr
    assert "pip install 'abh3-supervisor[foxglove]'" in done.stderr
    assert "startup" not in done.stderr  # no drive was started


# ------------------------------------------------------------------ the layout


def test_the_layouts_every_path_is_a_topic_and_field_its_configuration_serves() -> None:
    """docs/foxglove/abh3-layout.json, for configs/skid-steer-demo.yaml: each panel it
    places is configured, and each message path names a topic that configuration's run
    serves and a field of that topic's schema."""
    from abh3_supervisor.config import load_config
    from abh3_supervisor.runtime.ros_topics import SCHEMAS

    layout = json.loads((ROOT / "docs/foxglove/abh3-layout.json").read_text())
    cfg = load_config(ROOT / "configs/skid-steer-demo.yaml")
    bus = next(iter(cfg.buses))
    types = {
        **{f"/{u}/vel_fbk_ab": "abh3_can_interface/msg/Abh3Velocity" for u in cfg.units},
        **{f"/{r}/odom": "nav_msgs/msg/Odometry" for r in cfg.robots},
        f"/can/{bus}/rx": "can_msgs/msg/Frame",
        "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    }

    def placed(node: Any) -> list[str]:
        if isinstance(node, str):
            return [node]
        return placed(node["first"]) + placed(node["second"])

    panels = layout["configById"]
    assert sorted(placed(layout["layout"])) == sorted(panels)
    paths = [p["value"] for c in panels.values() for p in c.get("paths", [])]
    paths += [c[k] for c in panels.values() for k in ("topicPath", "topicToRender") if k in c]
    for path in paths:
        topic, *fields = path.split(".")
        assert topic in types, f"{path}: not a topic of {cfg.file}"
        words = SCHEMAS[types[topic]].split()
        assert all(f in words for f in fields), f"{path}: no such field"
    units = {p.split("/")[1] for p in paths if "vel_fbk_ab" in p}
    assert units == set(cfg.units)  # every unit has its plot
