"""A Foxglove WebSocket server of our own: the part of the protocol a watch-only live view
needs, on the ``websockets`` library, with a bounded queue per viewer that counts what
the viewer missed.

The protocol is Foxglove's WebSocket protocol v1 (github.com/foxglove/ws-protocol,
``docs/spec.md``): subprotocol ``foxglove.websocket.v1`` (``foxglove.sdk.v1``, the name
foxglove-sdk's servers answer to, is accepted too: the messages below are the same);
JSON ``serverInfo`` (no capability: nothing a viewer sends reaches the supervisor) and
``advertise`` (every channel on connecting, each later one as it is made) to the viewer;
``subscribe`` and ``unsubscribe`` from it; binary message data to it: opcode ``0x01``,
the subscription id (u32 LE), the message's time (u64 LE, ns), the payload. Anything
else a viewer sends is answered with a ``status`` message and said in the log (made
printable, short and rate-limited: :class:`ViewerLines`).

Everything here runs on one thread of its own with its own asyncio loop, at normal
priority: the bus loop does no per-viewer work. Each viewer has a queue of ``BACKLOG``
messages in front of its socket; when it is full the oldest message is dropped (a live
view is about now: the viewer that reads again sees the latest, not what was current
when it stopped — foxglove-sdk's choice too) and counted against that viewer
(:attr:`FoxgloveServer.viewers`), said when it starts, at most every ``REPORT_S`` while it
goes on, when it catches up, and at the end. ``websockets`` is imported only when a
server starts (the ``foxglove`` extra).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import errno
import json
import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from abh3_supervisor.runtime import priority

if TYPE_CHECKING:
    from websockets.asyncio.server import Server, ServerConnection

log = logging.getLogger(__name__)
SUBPROTOCOL = "foxglove.websocket.v1"  # the spec's name; Foxglove offers it
# in our order of preference: foxglove-sdk's servers speak only the second, and a client
# made for them (the app offers both) may offer only it
SUBPROTOCOLS = (SUBPROTOCOL, "foxglove.sdk.v1")
MESSAGE_DATA = 0x01  # the binary opcode: subscription id, time, payload
_HEADER = struct.Struct("<BIQ")
BACKLOG = 1024  # messages queued per viewer (~0.5 s of everything, 4 units at 100 Hz)
REPORT_S = 10.0  # a viewer's drop lines: at most one per this while it drops
CONTROL_MAX = 256  # a viewer's unsent status replies beyond which no more are queued
# the kernel's send buffer of each viewer's socket (Linux doubles it): what may wait
# there uncounted; autotuned, it reached 4 MB on loopback, and a viewer that never read
# had about 3 MB there (some 20 s of 4 units' topics) before its first drop was counted.
# Enough for any link a live view needs: 128 KiB a 50 ms round trip is 2.6 MB/s
SEND_BUFFER = 1 << 16
INCOMING_MAX = 1 << 16  # bytes of a viewer's message (a subscribe to every channel fits)
KEPT_GONE = 100  # viewers that left whose counts are kept (the most recent)
LINES_PER_S = 5  # lines a viewer's doing may add to the log a second, at most
LINE_CHARS = 300


class Watchers:
    """Which viewer subscribes to which channel: ``(viewer number, channel id)`` pairs,
    changed on the server's thread, read on the bus loop (``bool``: anyone at all)."""

    def __init__(self) -> None:
        self.subscriptions: set[tuple[int, int]] = set()

    def __bool__(self) -> bool:
        return bool(self.subscriptions)


class Channel:
    """A topic as advertised: id, schema, and the subscriptions to it (read on the bus
    loop: none, and the topic's messages are not even queued)."""

    __slots__ = ("advert", "id", "subscriptions", "topic")

    def __init__(self, number: int, topic: str, schema_name: str, schema: str) -> None:
        self.id, self.topic = number, topic
        self.advert = {
            "id": number,
            "topic": topic,
            "encoding": "cdr",
            "schemaName": schema_name,
            "schema": schema,
            "schemaEncoding": "ros2msg",
        }
        self.subscriptions: dict[tuple[int, int], Subscription] = {}  # (viewer, sub id)


class Subscription:
    __slots__ = ("active", "channel", "id")

    def __init__(self, number: int, channel: Channel) -> None:
        self.id, self.channel, self.active = number, channel, True


class ViewerLines:
    """Lines a viewer's doing adds to the log (it connects, leaves, sends what is not
    understood; ``websockets``' own lines): made printable and short (a viewer's text is
    in some: no forged lines, no terminal escapes), at most WARNING (a viewer's garbage
    is no error of ours), each said once in a row and at most ``LINES_PER_S`` a second,
    the rest counted into the next line said."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.last, self.window, self.said, self.unsaid = "", -math.inf, 0, 0

    def say(self, level: int, text: str) -> None:
        text = "".join(c if c.isprintable() else "?" for c in text)[:LINE_CHARS]
        now = self.clock()
        if now >= self.window:
            self.window, self.said = now + 1.0, 0
        if text == self.last or self.said >= LINES_PER_S:
            self.unsaid += 1
            return
        self.last, self.said = text, self.said + 1
        more = f" ({self.unsaid} more not shown)" if self.unsaid else ""
        self.unsaid = 0
        log.log(min(level, logging.WARNING), "foxglove: %s%s", text, more)


class _LibraryLines(logging.Handler):
    """``websockets``' lines (a handshake that failed, …), through :class:`ViewerLines`."""

    def __init__(self, lines: ViewerLines) -> None:
        super().__init__()
        self.lines = lines

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.say(record.levelno, record.getMessage())


class Viewer:
    """One connection: its queue, what it was sent and what it missed."""

    def __init__(self, number: int, address: str, ws: ServerConnection) -> None:
        self.id, self.ws = number, ws
        self.name = f"#{number} {address}"
        self.queue: collections.deque[tuple[Subscription, int, bytes]] = collections.deque()
        self.control: collections.deque[str] = collections.deque()  # JSON, never dropped
        self.subscriptions: dict[int, Subscription] = {}  # by the viewer's id
        self.sent = 0  # message data handed to the connection
        self.dropped = 0  # message data the full queue lost (and what the end cut off)
        self.wake = asyncio.Event()
        self.idle = asyncio.Event()  # nothing queued, nothing being sent
        # the log: behind (dropping, not caught up yet), and what was said of it
        self.behind = self.said_behind = False
        self.unsaid, self.quiet_until = 0, -math.inf

    def offer(self, sub: Subscription, ns: int, data: bytes) -> None:
        queue = self.queue
        if len(queue) >= BACKLOG:
            old = queue.popleft()  # the oldest: see the module's docstring
            if old[0].active:  # one unsubscribed from was not wanted any more
                self.dropped += 1
                self.unsaid += 1
                self.behind = True
        queue.append((sub, ns, data))
        self.idle.clear()
        self.wake.set()

    def tell(self, message: dict[str, Any]) -> None:
        self.control.append(json.dumps(message, separators=(",", ":")))
        self.idle.clear()
        self.wake.set()

    async def send(self) -> None:
        """The viewer's sender: control messages first, then its queue, in order."""
        from websockets.exceptions import ConnectionClosed

        ws, queue, control = self.ws, self.queue, self.control
        try:
            while True:
                if control:
                    await ws.send(control.popleft())
                elif queue:
                    sub, ns, data = queue.popleft()
                    if sub.active:  # sent: in the connection's buffer, before the wait
                        self.sent += 1
                        await ws.send(_HEADER.pack(MESSAGE_DATA, sub.id, ns) + data)
                else:
                    self.behind = False  # all it was given was sent: caught up
                    self.idle.set()
                    self.wake.clear()
                    await self.wake.wait()
        except ConnectionClosed:
            pass

    def report(self, now: float) -> None:
        """The viewer's drop lines: one when it starts dropping, then at most one every
        ``REPORT_S`` (still dropping, caught up)."""
        if now < self.quiet_until:
            return
        who = f"foxglove: viewer {self.name}"
        if self.behind and not self.said_behind:
            log.warning(
                "%s falls behind: its oldest messages are dropped (counted; the drives "
                "are unaffected)",
                who,
            )
        elif self.behind and self.unsaid:
            log.warning(
                "%s still falls behind: %d more message(s) dropped (%d in all)",
                who,
                self.unsaid,
                self.dropped,
            )
        elif not self.behind and self.said_behind:
            log.info("%s caught up; %d message(s) dropped in all", who, self.dropped)
        elif not self.behind and self.unsaid:  # behind, then caught up, since the last
            log.warning(
                "%s fell behind for a moment: %d message(s) dropped (%d in all)",
                who,
                self.unsaid,
                self.dropped,
            )
        else:
            return
        self.said_behind, self.unsaid, self.quiet_until = self.behind, 0, now + REPORT_S


class FoxgloveServer:
    """The server: :meth:`start` binds and serves on a thread of its own, calling
    ``tick`` every ``period`` there (where :meth:`publish` is called from); :meth:`stop`
    gives every viewer ``stop_s`` to take what is queued for it, cuts those that do not,
    and closes."""

    def __init__(
        self, name: str, host: str, port: int, schemas: Mapping[str, str], stop_s: float
    ) -> None:
        self.name, self.host, self.port, self.schemas = name, host, port, schemas
        self.stop_s = stop_s
        self.channels: dict[str, Channel] = {}  # topic → channel (read on the bus loop)
        self.watchers = Watchers()
        self.lines = ViewerLines()
        self.session = str(time.time_ns())  # a viewer tells a restart from a reconnect
        self._live: dict[int, Viewer] = {}
        self._gone: dict[str, tuple[int, int]] = {}  # name → (sent, dropped), the latest
        self._count = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
        self._error: Exception | None = None  # what start() raises
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ the caller's side

    def start(self, tick: Callable[[], None], period: float) -> None:
        """Bind and serve (on the server's thread), or raise why not (the bind's
        ``OSError``: the port is taken, the host is not this machine's)."""
        ready = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(tick, period, ready), name="foxglove server", daemon=True
        )
        self._thread.start()
        ready.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error

    def stop(self, timeout: float) -> bool:
        """Stop serving; False when the server's thread did not end within ``timeout``."""
        loop, stopping, thread = self._loop, self._stopping, self._thread
        if loop is not None and stopping is not None:
            with contextlib.suppress(RuntimeError):  # its loop is closed: it ended already
                loop.call_soon_threadsafe(stopping.set)
        if thread is None:
            return True
        thread.join(timeout)
        return not thread.is_alive()

    @property
    def viewers(self) -> dict[str, tuple[int, int]]:
        """Each viewer, connected or gone (the latest ``KEPT_GONE``), by its name
        (``#N host:port``): (messages sent to it, messages it missed)."""
        seen = dict(self._gone)
        seen.update((v.name, (v.sent, v.dropped)) for v in list(self._live.values()))
        return seen

    # ------------------------------------------------------------------ on the server's thread

    def publish(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        """``data`` to every viewer subscribed to ``topic``'s channel, made and advertised
        the first time (a ``schema`` unknown raises ``KeyError``)."""
        channel = self.channels.get(topic)
        if channel is None:
            channel = Channel(len(self.channels) + 1, topic, schema, self.schemas[schema])
            self.channels[topic] = channel
            for viewer in self._live.values():
                viewer.tell({"op": "advertise", "channels": [channel.advert]})
        for sub_key, sub in channel.subscriptions.items():
            self._live[sub_key[0]].offer(sub, ns, data)

    def _run(self, tick: Callable[[], None], period: float, ready: threading.Event) -> None:
        priority.normal()  # never the bus loop's real-time priority (it inherits it)
        try:
            asyncio.run(self._main(tick, period, ready))
        except Exception as exc:  # the live view ends; the drives are not concerned
            if ready.is_set():
                log.exception("foxglove: the live view failed; the drives are unaffected")
            else:
                self._error = exc
        finally:
            ready.set()

    async def _main(self, tick: Callable[[], None], period: float, ready: threading.Event) -> None:
        from websockets.asyncio.server import serve
        from websockets.typing import Subprotocol

        library = logging.getLogger(f"{__name__}.websockets")
        for handler in list(library.handlers):  # an earlier server's, in this process
            library.removeHandler(handler)
        library.addHandler(_LibraryLines(self.lines))
        library.setLevel(logging.WARNING)  # not its INFO lines: ours say a viewer came
        library.propagate = False
        try:
            server = await serve(
                self._serve,
                self.host,
                self.port,
                subprotocols=[Subprotocol(s) for s in SUBPROTOCOLS],
                compression=None,  # each message compressed per viewer: CPU the robot needs
                max_size=INCOMING_MAX,
                close_timeout=self.stop_s,
                logger=library,
                server_header=None,
            )
        except OSError as exc:
            self._error = exc
            return
        self.port = server.sockets[0].getsockname()[1]
        self._loop, self._stopping = asyncio.get_running_loop(), asyncio.Event()
        ready.set()
        ticking = asyncio.ensure_future(self._tick(tick, period))
        await self._stopping.wait()
        ticking.cancel()
        tick()  # the stop frames, last
        await self._close(server)

    async def _tick(self, tick: Callable[[], None], period: float) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(period)
            try:
                tick()
            except Exception:  # never the end of the live view (FoxgloveSink.drain says why)
                log.exception("foxglove: handing messages to the viewers failed")
            now = loop.time()
            for viewer in list(self._live.values()):
                viewer.report(now)

    async def _close(self, server: Server) -> None:
        """Each viewer gets ``stop_s`` to take what is queued for it; one that does not is
        cut (what it did not get is counted as missed); the others are closed."""
        viewers = list(self._live.values())
        if viewers:
            await asyncio.wait(
                [asyncio.ensure_future(v.idle.wait()) for v in viewers], timeout=self.stop_s
            )
        for viewer in viewers:
            if viewer.idle.is_set() or viewer.id not in self._live:
                continue
            viewer.dropped += sum(1 for sub, _, _ in viewer.queue if sub.active)
            viewer.queue.clear()
            self.lines.say(
                logging.WARNING,
                f"viewer {viewer.name} does not let go: its connection is cut",
            )
            viewer.ws.transport.abort()
        server.close()
        try:
            await asyncio.wait_for(server.wait_closed(), 2 * self.stop_s)
        except TimeoutError:
            log.warning("foxglove: a viewer does not let go: its connection is left behind")

    async def _serve(self, ws: ServerConnection) -> None:
        """One viewer, from its handshake to its going."""
        from websockets.exceptions import ConnectionClosed

        sock = ws.transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        self._count += 1
        viewer = Viewer(self._count, _address(ws.remote_address), ws)
        self._live[viewer.id] = viewer
        self.lines.say(logging.INFO, f"viewer {viewer.name} connected")
        viewer.tell(
            {
                "op": "serverInfo",
                "name": self.name,
                "capabilities": [],  # watch only: no publishing, services or parameters
                "metadata": {},
                "sessionId": self.session,
            }
        )
        viewer.tell({"op": "advertise", "channels": [c.advert for c in self.channels.values()]})
        sender = asyncio.ensure_future(viewer.send())
        try:
            async for message in ws:
                if isinstance(message, str):
                    self._on_text(viewer, message)
                else:
                    self._refuse(viewer, 1, "binary messages are not accepted (watch only)")
        except ConnectionClosed:  # it went without a close frame, or was cut
            pass
        finally:
            sender.cancel()
            viewer.idle.set()  # nothing more goes to it: the stop does not wait for it
            for sub in viewer.subscriptions.values():
                self._drop_subscription(viewer, sub)
            del self._live[viewer.id]
            self._gone[viewer.name] = (viewer.sent, viewer.dropped)
            while len(self._gone) > KEPT_GONE:
                del self._gone[next(iter(self._gone))]
            missed = f", {viewer.dropped} missed" if viewer.dropped else ""
            self.lines.say(logging.INFO, f"viewer {viewer.name} left ({viewer.sent} sent{missed})")

    def _on_text(self, viewer: Viewer, text: str) -> None:
        try:
            message = json.loads(text)
        except ValueError:
            return self._refuse(viewer, 2, "not JSON")
        op = message.get("op") if isinstance(message, dict) else None
        if op == "subscribe":
            for item in _items(message, "subscriptions"):
                self._subscribe(viewer, item)
        elif op == "unsubscribe":
            for number in _items(message, "subscriptionIds"):
                sub = viewer.subscriptions.get(number) if _u32(number) else None
                if sub is None:
                    self._refuse(viewer, 1, f"unsubscribe: no subscription {number!r}")
                else:
                    self._drop_subscription(viewer, sub)
                    del viewer.subscriptions[number]
        else:
            self._refuse(viewer, 1, f"op {op!r} is not supported (watch only)")

    def _subscribe(self, viewer: Viewer, item: object) -> None:
        number = item.get("id") if isinstance(item, dict) else None
        channel_id = item.get("channelId") if isinstance(item, dict) else None
        if not _u32(number) or not isinstance(channel_id, int):
            return self._refuse(viewer, 2, f"subscribe: not an id and a channelId: {item!r}")
        assert isinstance(number, int)
        channel = next((c for c in self.channels.values() if c.id == channel_id), None)
        if channel is None:
            return self._refuse(viewer, 2, f"subscribe: no channel {channel_id}")
        if number in viewer.subscriptions:
            return self._refuse(viewer, 2, f"subscribe: subscription {number} is in use")
        if any(s.channel is channel for s in viewer.subscriptions.values()):
            return self._refuse(viewer, 2, f"subscribe: channel {channel_id} is subscribed to")
        sub = viewer.subscriptions[number] = Subscription(number, channel)
        channel.subscriptions[(viewer.id, number)] = sub
        self.watchers.subscriptions.add((viewer.id, channel.id))

    def _drop_subscription(self, viewer: Viewer, sub: Subscription) -> None:
        sub.active = False  # what is queued for it is not sent
        sub.channel.subscriptions.pop((viewer.id, sub.id), None)
        self.watchers.subscriptions.discard((viewer.id, sub.channel.id))

    def _refuse(self, viewer: Viewer, level: int, why: str) -> None:
        """A viewer's message not acted on: a status message to it, a line in the log."""
        self.lines.say(logging.WARNING, f"viewer {viewer.name}: {why}")
        if len(viewer.control) < CONTROL_MAX:  # one that does not read gets no more
            viewer.tell({"op": "status", "level": level, "message": why[:LINE_CHARS]})


def _items(message: dict[str, Any], key: str) -> list[Any]:
    items = message.get(key)
    return items if isinstance(items, list) else []


def _u32(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 1 << 32


def _address(peer: Any) -> str:
    """``host:port`` (``[host]:port`` for IPv6) of a connection's peer."""
    if isinstance(peer, tuple) and len(peer) >= 2:
        host, port = peer[0], peer[1]
        return f"[{host}]:{port}" if ":" in str(host) else f"{host}:{port}"
    return str(peer)


def bind_error(exc: OSError, host: str, port: int) -> str:
    """What a user can act on, of a bind that failed."""
    if exc.errno == errno.EADDRINUSE:
        return f"port {port} on {host} is in use"
    if exc.errno == errno.EADDRNOTAVAIL:
        return f"{host} is not an address of this machine"
    return exc.strerror or str(exc)
