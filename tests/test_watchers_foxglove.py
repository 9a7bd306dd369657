"""Each Foxglove viewer's own queue (runtime/foxglove_server.py), against real
``websockets`` clients: a viewer that never reads has what it misses counted and said,
while one that reads gets every message; unsubscribing and leaving stop the flow; a
channel made later is advertised; the log says when a viewer falls behind, how it goes
on and when it catches up.

The test plays the bus loop: it writes to the sink as the producer does, in batches it
lets the server's thread take (the hand-off queue never drops here). Conditions are
polled; ``WAIT_S`` only turns a hang into a failure.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import socket
import struct
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from typing import Any, TypeVar

import pytest

from abh3_supervisor.config.endpoint import Endpoint
from abh3_supervisor.runtime import foxglove_server
from abh3_supervisor.runtime.foxglove_live import FoxgloveLive, start_foxglove
from abh3_supervisor.runtime.ros_topics import FRAME, SCHEMAS, VELOCITY

pytest.importorskip("websockets")
import websockets
from websockets.typing import Subprotocol

pytestmark = pytest.mark.wallclock
T = TypeVar("T")
WAIT_S = 60.0  # a condition not met by then is a failure, not a slow machine
RX, FBK = "/can/demo/rx", "/left/vel_fbk_ab"
PAD = bytes(200)  # a message's size: about a frame's and a feedback's CDR, and more


def payload(i: int) -> bytes:
    return struct.pack("<I", i) + PAD


async def until(check: Callable[[], bool]) -> None:
    """Poll ``check`` (the server runs on a thread of its own)."""
    async with asyncio.timeout(WAIT_S):
        while not check():
            await asyncio.sleep(0.005)


async def feed(live: FoxgloveLive, topic: str, start: int, count: int) -> None:
    """``count`` messages to ``topic``, numbered from ``start``, as the bus loop writes
    them; back once the server's thread has taken them all."""
    for i in range(start, start + count):
        live.sink.write(topic, FRAME if topic == RX else VELOCITY, payload(i), i)
    await until(lambda: not live.sink.queue)


@asynccontextmanager
async def serving() -> AsyncIterator[FoxgloveLive]:
    live = start_foxglove(Endpoint("127.0.0.1", 0), "test", SCHEMAS)
    try:
        yield live
    finally:
        await asyncio.to_thread(live.stop)  # the viewers of this loop go on reading


class Client:
    """A viewer: the channels advertised, its subscriptions, what it received."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}
        self.info: dict[str, Any] = {}
        self.statuses: list[dict[str, Any]] = []
        self.topics: dict[int, str] = {}  # subscription id → topic
        self.received: list[tuple[str, int, int]] = []  # topic, ns, payload's number

    @property
    def name_suffix(self) -> str:
        host, port = self.ws.local_address[:2]
        return f" {host}:{port}"

    async def next(self) -> Any:
        raw = await asyncio.wait_for(self.ws.recv(), WAIT_S)
        if isinstance(raw, bytes):
            opcode, sub, ns = struct.unpack_from("<BIQ", raw)
            assert opcode == foxglove_server.MESSAGE_DATA
            (number,) = struct.unpack_from("<I", raw, 13)
            assert raw[17:] == PAD
            self.received.append((self.topics[sub], ns, number))
            return raw
        message = json.loads(raw)
        if message["op"] == "serverInfo":
            self.info = message
        elif message["op"] == "advertise":
            self.channels.update((c["topic"], c) for c in message["channels"])
        elif message["op"] == "status":
            self.statuses.append(message)
        return message

    async def subscribe(self, topic: str, sub: int) -> None:
        while topic not in self.channels:
            await self.next()
        self.topics[sub] = topic
        channel = self.channels[topic]["id"]
        await self.send({"op": "subscribe", "subscriptions": [{"id": sub, "channelId": channel}]})

    async def send(self, message: dict[str, Any]) -> None:
        await self.ws.send(json.dumps(message))

    async def read_until(self, check: Callable[[], bool]) -> None:
        while not check():
            await self.next()


def connect(live: FoxgloveLive, **options: Any) -> Any:
    subprotocols = options.pop("subprotocols", [foxglove_server.SUBPROTOCOL])
    return websockets.connect(
        f"ws://127.0.0.1:{live.port}",
        subprotocols=[Subprotocol(s) for s in subprotocols],
        **options,
    )


def viewer(live: FoxgloveLive, client: Client) -> tuple[str, tuple[int, int]]:
    """The server's name and counts of ``client``."""
    found = [(n, c) for n, c in live.viewers.items() if n.endswith(client.name_suffix)]
    assert len(found) == 1, live.viewers
    return found[0]


def run(test: Callable[[], Awaitable[T]]) -> T:
    return asyncio.run(test())  # type: ignore[arg-type]


def stalled_socket(live: FoxgloveLive) -> socket.socket:
    """A connected socket whose receive buffer fills at once (a viewer that never
    reads: the client library stops reading it at one message queued)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", live.port))
    return sock


# ------------------------------------------------------------------ a viewer that never reads


def test_a_viewer_that_never_reads_has_its_drops_counted_and_one_that_reads_gets_all(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Both subscribe to the same topic; one never reads again. It drops (its oldest
    messages), counted and said once when it starts; the reader gets every message, in
    order, none dropped; at the stop the stalled one is cut, all it was given is either
    sent or counted as missed, and the log says its count."""

    async def test() -> tuple[int, tuple[int, int], tuple[int, int], str, str]:
        async with serving() as live:
            await feed(live, RX, 0, 1)  # the channel is made (nobody watches: not sent)
            async with (
                connect(live) as r,
                connect(live, sock=stalled_socket(live), max_queue=1, close_timeout=0) as s,
            ):
                reader, stalled = Client(r), Client(s)
                await reader.subscribe(RX, 7)
                await stalled.subscribe(RX, 9)  # and reads nothing from here on
                await until(lambda: len(live.watchers.subscriptions) == 2)
                reading = asyncio.ensure_future(reader.read_until(lambda: False))
                sent = 1
                while viewer(live, stalled)[1][1] < 2 * foxglove_server.BACKLOG:
                    assert sent < 500_000, "the stalled viewer never dropped"
                    await feed(live, RX, sent, 500)
                    sent += 500
                await until(lambda: len(reader.received) == sent - 1)
                reading.cancel()
                assert live.sink.dropped == 0  # the hand-off queue: never full here
                assert viewer(live, reader)[1] == (sent - 1, 0)
                numbers = [number for _, _, number in reader.received]
                assert numbers == list(range(1, sent))  # every one, in order
                assert {t for t, _, _ in reader.received} == {RX}
                await asyncio.to_thread(live.stop)  # the reader has all: it closes at once
                name, counts = viewer(live, stalled)
                return sent - 1, counts, viewer(live, reader)[1], name, viewer(live, reader)[0]

    with caplog.at_level(logging.INFO, logger="abh3_supervisor.runtime"):
        given, (sent, missed), reader, name, reader_name = run(test)
    assert reader == (given, 0)
    assert missed > 2 * foxglove_server.BACKLOG and sent + missed == given
    lines = [r.getMessage() for r in caplog.records]
    behind = [line for line in lines if "falls behind" in line]
    assert behind == [
        f"foxglove: viewer {name} falls behind: its oldest messages are dropped "
        "(counted; the drives are unaffected)"
    ]
    assert f"foxglove: viewer {name} does not let go: its connection is cut" in lines
    assert f"foxglove: viewer {name} missed {missed} of {given} message(s)" in lines
    assert not [line for line in lines if reader_name in line and "miss" in line]


def test_a_viewer_that_reads_again_catches_up_and_the_log_says_so(
    caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """It stops reading (drops, said), then reads again: the log says it caught up and
    what it missed; it gets the newest messages (the oldest were dropped)."""
    monkeypatch.setattr(foxglove_server, "REPORT_S", 0.01)  # no quiet time between lines

    async def test_reads_again() -> tuple[str, int, int, list[int]]:
        async with serving() as live:
            await feed(live, FBK, 0, 1)
            async with connect(live, sock=stalled_socket(live), max_queue=1, close_timeout=0) as ws:
                client = Client(ws)
                await client.subscribe(FBK, 1)
                await until(lambda: bool(live.watchers))
                sent = 1
                while viewer(live, client)[1][1] == 0:
                    assert sent < 500_000, "it never dropped"
                    await feed(live, FBK, sent, 500)
                    sent += 500
                name = viewer(live, client)[0]
                await until(lambda: f"viewer {name} falls behind" in caplog.text)
                # it reads again: what it is given is what was sent to it, no more
                await client.read_until(lambda: len(client.received) == viewer(live, client)[1][0])
                await until(lambda: f"viewer {name} caught up" in caplog.text)
                missed = viewer(live, client)[1][1]
                return name, sent - 1, missed, [n for *_, n in client.received]

    with caplog.at_level(logging.INFO, logger="abh3_supervisor.runtime"):
        name, given, missed, numbers = run(test_reads_again)
    assert len(numbers) + missed == given
    assert numbers == sorted(numbers) and numbers[-1] == given  # the newest, in order
    assert numbers[-1] - numbers[0] + 1 > len(numbers)  # a gap: the oldest were dropped
    assert f"foxglove: viewer {name} caught up; {missed} message(s) dropped in all" in (caplog.text)


def test_the_drop_lines_start_go_on_at_most_every_report_s_and_end(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """One line when a viewer starts dropping, then at most one every REPORT_S: still
    dropping (how many more), caught up, or fell behind for a moment in between."""
    viewer = foxglove_server.Viewer(3, "127.0.0.1:5555", ws=None)  # type: ignore[arg-type]
    channel = foxglove_server.Channel(1, RX, FRAME, SCHEMAS[FRAME])
    sub = foxglove_server.Subscription(1, channel)
    report_s = foxglove_server.REPORT_S

    def offer(count: int) -> None:
        for _ in range(count):
            viewer.offer(sub, 0, b"")

    with caplog.at_level(logging.INFO, logger=foxglove_server.log.name):
        offer(foxglove_server.BACKLOG + 5)  # 5 dropped
        viewer.report(0.0)
        offer(3)
        viewer.report(report_s / 2)  # quiet: counted for the next line
        viewer.report(report_s)
        viewer.report(2 * report_s)  # nothing new: nothing said
        viewer.queue.clear()
        viewer.behind = False  # what its sender does once all it was given is sent
        viewer.report(3 * report_s)
        offer(foxglove_server.BACKLOG + 2)  # behind again, and caught up before a line
        viewer.queue.clear()
        viewer.behind = False
        viewer.report(3.5 * report_s)  # quiet still
        viewer.report(4 * report_s)
    said = [r.getMessage() for r in caplog.records]
    who = "foxglove: viewer #3 127.0.0.1:5555"
    assert said == [
        f"{who} falls behind: its oldest messages are dropped (counted; the drives are unaffected)",
        f"{who} still falls behind: 3 more message(s) dropped (8 in all)",
        f"{who} caught up; 8 message(s) dropped in all",
        f"{who} fell behind for a moment: 2 message(s) dropped (10 in all)",
    ]
    assert viewer.dropped == 10


# ------------------------------------------------------------------ subscriptions


def test_unsubscribing_and_leaving_stop_the_flow_and_the_topic_is_not_queued() -> None:
    """After an unsubscribe, nothing of that subscription arrives; once no viewer
    subscribes to a topic, the bus loop's write does not even queue it; a viewer that
    leaves takes its subscriptions with it, and its counts stay."""

    async def test() -> None:
        async with serving() as live:
            await feed(live, RX, 0, 1)
            await feed(live, FBK, 0, 1)
            async with connect(live) as ws:
                client = Client(ws)
                await client.subscribe(RX, 1)
                await until(lambda: bool(live.watchers))
                await feed(live, RX, 1, 10)
                await client.read_until(lambda: len(client.received) == 10)
                await client.send({"op": "unsubscribe", "subscriptionIds": [1]})
                await until(lambda: not live.watchers)
                live.sink.write(RX, FRAME, payload(99), 99)
                assert not live.sink.queue  # nobody watches it: not even queued
                await client.subscribe(FBK, 1)  # the id may be used again
                await until(lambda: bool(live.watchers))
                await feed(live, RX, 11, 5)
                await feed(live, FBK, 1, 1)
                await client.read_until(lambda: len(client.received) == 11)
                assert client.received[-1][0] == FBK  # nothing of the old subscription
                assert viewer(live, client)[1] == (11, 0)
                name = viewer(live, client)[0]
            await until(lambda: not live.watchers)  # it left: its subscription went
            assert live.viewers[name] == (11, 0)
            live.sink.write(FBK, VELOCITY, payload(1), 1)
            assert not live.sink.queue

    run(test)


def test_what_a_viewer_may_not_do_is_answered_with_a_status_and_never_acted_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A channel that does not exist, a subscription id in use, a second subscription
    to a channel, an unknown subscription, an op the server does not offer, a binary
    message, text that is not JSON: each a status message, the connection kept."""

    async def test() -> list[dict[str, Any]]:
        async with serving() as live:
            await feed(live, RX, 0, 1)
            await feed(live, FBK, 0, 1)
            async with connect(live) as ws:
                client = Client(ws)
                await client.subscribe(RX, 1)
                fbk = client.channels[FBK]["id"]
                rx = client.channels[RX]["id"]
                for wrong in (
                    {"op": "subscribe", "subscriptions": [{"id": 2, "channelId": 999}]},
                    {"op": "subscribe", "subscriptions": [{"id": 1, "channelId": fbk}]},
                    {"op": "subscribe", "subscriptions": [{"id": 2, "channelId": rx}]},
                    {"op": "subscribe", "subscriptions": [{"id": -1, "channelId": fbk}]},
                    {"op": "unsubscribe", "subscriptionIds": [5]},
                    {"op": "advertise", "channels": []},
                ):
                    await client.send(wrong)
                await ws.send(b"\x01\x00\x00\x00\x00")
                await ws.send("{not json")
                await client.read_until(lambda: len(client.statuses) == 8)
                assert live.watchers.subscriptions == {(1, rx)}  # only the first
                await feed(live, RX, 1, 1)
                await client.read_until(lambda: len(client.received) == 1)
                return client.statuses

    with caplog.at_level(logging.INFO, logger="abh3_supervisor.runtime"):
        statuses = run(test)
    assert [s["level"] for s in statuses] == [2, 2, 2, 2, 1, 1, 1, 2]
    assert "no channel 999" in statuses[0]["message"]
    assert "subscription 1 is in use" in statuses[1]["message"]
    assert "is subscribed to" in statuses[2]["message"]
    assert "'advertise' is not supported" in statuses[5]["message"]
    assert "foxglove: viewer #1 127.0.0.1:" in caplog.text  # said in the log too


# ------------------------------------------------------------------ the protocol


def test_a_channel_made_later_is_advertised_and_its_messages_framed_as_the_spec_says() -> None:
    """serverInfo, an advertise on connecting (empty: no topic yet), the channel of a
    topic when it is first written, then message data: opcode 0x01, the subscription id
    (u32 LE), the message's time (u64 LE ns), the CDR bytes."""

    async def test() -> tuple[Client, list[Any], bytes]:
        async with serving() as live, connect(live) as ws:
            assert ws.subprotocol == "foxglove.websocket.v1"
            client = Client(ws)
            first = [await client.next(), await client.next()]
            await feed(live, FBK, 0, 1)  # a topic appears
            await client.subscribe(FBK, 0x01020304)
            await until(lambda: bool(live.watchers))
            live.sink.write(FBK, VELOCITY, b"\x00\x01cdr", 0x1122334455667788)
            raw = await asyncio.wait_for(ws.recv(), WAIT_S)  # not one of feed()'s
            assert isinstance(raw, bytes)
            return client, first, raw

    client, first, raw = run(test)
    assert first[0]["op"] == "serverInfo" and first[0]["name"] == "test"
    assert first[0]["capabilities"] == [] and "supportedEncodings" not in first[0]
    assert first[1] == {"op": "advertise", "channels": []}
    assert client.channels[FBK] == {
        "id": 1,
        "topic": FBK,
        "encoding": "cdr",
        "schemaName": VELOCITY,
        "schema": SCHEMAS[VELOCITY],
        "schemaEncoding": "ros2msg",
    }
    assert raw == b"\x01" + bytes([4, 3, 2, 1]) + bytes.fromhex("8877665544332211") + b"\x00\x01cdr"


def test_either_subprotocol_name_is_served_and_none_is_refused() -> None:
    """foxglove.websocket.v1 (the spec's) first; foxglove.sdk.v1 (foxglove-sdk's
    servers', which a client made for them may offer alone) too; no subprotocol: 400."""

    async def test() -> list[str | None]:
        chosen = []
        async with serving() as live:
            for offered in (
                ["foxglove.sdk.v1", "foxglove.websocket.v1"],
                ["foxglove.sdk.v1"],
            ):
                async with connect(live, subprotocols=offered) as ws:
                    assert json.loads(await ws.recv())["op"] == "serverInfo"
                    chosen.append(ws.subprotocol)
            with pytest.raises(websockets.InvalidStatus, match="400"):
                async with websockets.connect(f"ws://127.0.0.1:{live.port}"):
                    pass
        return chosen

    assert run(test) == ["foxglove.websocket.v1", "foxglove.sdk.v1"]


# ------------------------------------------------------------------ in a run


def test_in_a_run_a_viewer_that_never_reads_is_counted_and_the_end_says_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The drives at 100 Hz, a viewer subscribed to everything that never reads: the
    run goes on until it has dropped; the stop says what it missed, as its count."""
    from abh3_supervisor.runtime.bus_runtime import Runtime
    from tests.support.foxglove import config

    async def test() -> tuple[str, int]:
        cfg = config()
        async with Runtime(cfg, foxglove=cfg.foxglove) as rt:
            live = rt.foxglove
            assert live is not None
            stop = asyncio.Event()
            running = asyncio.ensure_future(rt.run_until(stop))
            try:
                async with connect(
                    live, sock=stalled_socket(live), max_queue=1, close_timeout=0
                ) as ws:
                    client = Client(ws)
                    await client.read_until(lambda: {RX, FBK} <= set(client.channels))
                    for sub, topic in enumerate(list(client.channels), 1):
                        await client.subscribe(topic, sub)
                    await until(lambda: viewer(live, client)[1][1] > 0)
                    name = viewer(live, client)[0]
                    stop.set()
                    await running
            finally:
                stop.set()
                await running
        counts = live.viewers[name]
        return name, counts[1]

    with caplog.at_level(logging.INFO, logger="abh3_supervisor.runtime"):
        name, missed = run(test)
    said = re.search(
        rf"foxglove: viewer {re.escape(name)} missed (\d+) of \d+ message", caplog.text
    )
    assert said is not None and int(said[1]) == missed > 0
