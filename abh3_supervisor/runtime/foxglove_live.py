"""``--foxglove [HOST:]PORT``: the MCAP recording's topics, live, over the Foxglove
WebSocket protocol (``foxglove-sdk``'s server), without ROS.

The same CDR messages and ``ros2msg`` schemas the recording writes (they come from the
one producer, :mod:`.ros_topics`), one channel per topic, made the first time the topic
is written. The server accepts no commands: it advertises no capability (no client
publishing, services or parameters), so a viewer can only watch.

A slow or absent viewer costs the bus nothing. Without an ``.mcap`` recording, the
high-rate topics (frames, feedback) are not even produced while no viewer subscribes
(:class:`LiveFeed`). The SDK's log call is cheap while nobody
watches (0.1 µs, the GIL kept) but not once a viewer subscribes: it wakes the SDK's
sender and gives up the GIL, 10 µs typically and up to milliseconds when another thread
takes the GIL meanwhile (docs/foxglove.md, measured). So :meth:`FoxgloveSink.write`, on
the bus loop, only appends the message to a bounded queue — nothing at all for a topic no
viewer subscribes to — and a thread of ours at normal priority hands the queue to the SDK
every ``DRAIN_S``. A full queue (that thread starved) drops the message, counts it and
says so once. Beyond that, each viewer has its own queue in the SDK (``BACKLOG``): one
that falls behind loses its oldest messages there, which the SDK says in the log
(``outbox for client … full``, at most every 30 s) but does not count — what the viewer
received against :attr:`FoxgloveSink.served` does. ``foxglove`` is imported only here,
only when asked for.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, TypeVar, cast

import can

from abh3_supervisor.config.endpoint import Endpoint
from abh3_supervisor.config.model import Config
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import Abh3Error, install_hint
from abh3_supervisor.runtime import priority
from abh3_supervisor.runtime.recorder import GuardedRecorder
from abh3_supervisor.runtime.ros_topics import SCHEMAS, RosTopics, TopicSink
from abh3_supervisor.scheduler.core import FeedbackEvent

if TYPE_CHECKING:
    import foxglove
    from foxglove.websocket import ServerListener, WebSocketServer

T = TypeVar("T")
log = logging.getLogger(__name__)
INSTALL_HINT = install_hint("foxglove")
SUBPROTOCOL = "foxglove.sdk.v1"  # what foxglove-sdk's server speaks (the app does)
BACKLOG = 1024  # messages the SDK queues per viewer (its default); the oldest go beyond
QUEUE = 8192  # messages waiting for the drain: ~8 s of 4 units at 100 Hz
DRAIN_S = 0.02  # the live view's added latency; 50 wake-ups a second, not one a message
STOP_S = 1.0  # what closing waits for the drain thread at most, and for the server
SDK_LINES_PER_S = 5  # the SDK's log lines said a second at most (a viewer may flood them)
SDK_LINE_CHARS = 300


def check_installed(option: str) -> None:
    """Say now, before anything opens, that the extra is missing (exit 2)."""
    try:
        import foxglove  # noqa: F401
    except ImportError as exc:
        raise Abh3Error(
            f"{option}: live view in Foxglove needs foxglove-sdk: {INSTALL_HINT}"
            f" ({exc.name or exc} is not installed)"
        ) from exc


Message = tuple[str, str, bytes, int]  # topic, schema, CDR bytes, wall-clock ns


class FoxgloveSink:
    """A :class:`~.ros_topics.TopicSink`: each topic's CDR messages queued on the bus
    loop and logged, by :meth:`drain` on a thread of ours, on the topic's own channel of
    ``context``, which the server serves."""

    def __init__(self, context: foxglove.Context, schemas: Mapping[str, str]) -> None:
        self.context = context
        self.schemas = schemas  # ROS 2 type name → ros2msg text
        self.queue: collections.deque[Message] = collections.deque()
        self.served = 0  # messages handed to the SDK (each viewer gets them, or drops)
        self.dropped = 0  # messages the full queue turned away (on the loop)
        self.failed = 0  # messages the SDK refused (said once)
        # topic → its channel's has_sinks, once the drain made the channel: until then
        # every message of the topic is queued (the channel must exist to be advertised)
        self._watched: dict[str, Callable[[], bool]] = {}
        self._log: dict[str, Callable[[bytes, int | None], None]] = {}

    def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        """On the bus loop: never blocks, never raises, never calls the SDK's log."""
        watched = self._watched.get(topic)
        if watched is not None and not watched():
            return  # nobody subscribes to this topic
        if len(self.queue) >= QUEUE:
            self.dropped += 1
            if self.dropped == 1:
                log.warning(
                    "foxglove: the live view falls behind: messages are dropped (counted, "
                    "said at the end); the drives are unaffected"
                )
            return
        self.queue.append((topic, schema, data, ns))

    def drain(self) -> None:
        """Hand what is queued to the SDK (on the drain thread)."""
        queue = self.queue
        while queue:
            topic, schema, data, ns = queue.popleft()
            try:
                send = self._log.get(topic)
                if send is None:
                    send = self._channel(topic, schema)
                send(data, ns)
            except Exception as exc:  # a viewer's trouble is never the bus's
                self.failed += 1
                if self.failed == 1:
                    log.error(
                        "foxglove: %s: not served (%s); the drives are unaffected", topic, exc
                    )
                continue
            self.served += 1

    def _channel(self, topic: str, schema: str) -> Callable[[bytes, int | None], None]:
        import foxglove

        channel = foxglove.Channel(
            topic,
            schema=foxglove.Schema(
                name=schema, encoding="ros2msg", data=self.schemas[schema].encode()
            ),
            message_encoding="cdr",
            context=self.context,
        )
        send = self._log[topic] = channel.base.log  # without the wrapper's type checks
        self._watched[topic] = channel.base.has_sinks  # 0.1 µs, keeps the GIL
        return send


class Watchers:
    """The server's listener: which viewer subscribes to which channel (called on the
    SDK's threads, with the GIL; read on the loop)."""

    def __init__(self) -> None:
        self.subscriptions: set[tuple[int, int]] = set()  # (client id, channel id)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.subscriptions.add((client.id, channel.id))

    def on_unsubscribe(self, client: Any, channel: Any) -> None:  # a viewer gone, too
        self.subscriptions.discard((client.id, channel.id))

    def __bool__(self) -> bool:
        return bool(self.subscriptions)


class LiveFeed(can.Listener):
    """The bus pumps' listener (the recorder's frames too) and a supervisor subscriber
    (after the recorder's), on the loop.

    The recording's topics (``shared``) reach the view through the recording — until it
    fails (a full disk): from the next frame or event on they come this way, so the live
    view goes on, each message once. Topics of its own (no ``.mcap`` recording) are not
    even produced while no viewer subscribes to anything (``watchers`` empty), but for
    the first frame of each bus and direction and the first feedback of each unit, which
    make their topics' channels, for a viewer to see and subscribe to; the status
    packets still go through (each robot's odometry adds up every pulse count)."""

    def __init__(
        self,
        topics: RosTopics,
        recorder: GuardedRecorder | None,
        *,
        shared: bool,
        watchers: Watchers | None = None,
    ) -> None:
        self.topics, self.recorder, self.shared = topics, recorder, shared
        self.watchers = watchers if watchers is not None and not shared else None
        self._direct = not shared  # whether the topics come this way (see _note)
        self._made: set[object] = set()  # what made its topics while nobody watched

    def _note(self) -> None:
        # read after the recorder had the frame or event: the one it failed on reached
        # the view through it; the next ones come this way — unless the topics are the
        # recording's, which its recorder goes on producing for the view after its file
        # failed (recorder.GuardedRecorder._taking)
        if self.recorder is not None and self.recorder.failed is not None and not self.shared:
            self._direct = True

    def _unwatched(self, key: object) -> bool:
        """Nobody watches, and ``key``'s topics are made: nothing to produce."""
        if self.watchers is None or self.watchers:
            return False
        if key in self._made:
            return True
        self._made.add(key)
        return False

    def on_message_received(self, msg: can.Message) -> None:
        direct = self._direct
        if self.recorder is not None:
            self.recorder.on_message_received(msg)
            self._note()
        if direct and not self._unwatched((msg.channel, msg.is_rx)):
            self.topics.on_message_received(msg)

    def attach(self, sup: Supervisor, clock: Callable[[], float]) -> None:
        if not self.shared:  # the recording attaches its own
            self.topics.attach(sup, clock)

    def observe(self, event: object) -> None:
        direct = self._direct
        self._note()  # the recorder had this event already
        if not direct:
            return
        if isinstance(event, FeedbackEvent) and self._unwatched(event.unit):
            return
        self.topics.observe(event)


def live_feed(
    sink: TopicSink,
    recorder: GuardedRecorder | None,
    config: Config,
    watchers: Watchers | None = None,
) -> LiveFeed:
    """The feed of ``sink``: the recording's topics when it makes them (``.mcap``: each
    message encoded once, for both), otherwise a producer of its own, idle while
    ``watchers`` is empty."""
    shared = getattr(recorder.writer, "topics", None) if recorder is not None else None
    if isinstance(shared, RosTopics):
        shared.sinks.append(sink)
        return LiveFeed(shared, recorder, shared=True)
    return LiveFeed(RosTopics(config, [sink]), recorder, shared=False, watchers=watchers)


class FoxgloveLive:
    """The server, the sink that feeds it and the thread that drains the sink's queue
    every ``DRAIN_S``; :meth:`stop` ends both."""

    def __init__(
        self, server: WebSocketServer, sink: FoxgloveSink, endpoint: Endpoint, watchers: Watchers
    ) -> None:
        self.server, self.sink, self.endpoint, self.watchers = server, sink, endpoint, watchers
        self._stopping = threading.Event()
        self._drainer = threading.Thread(target=self._drain, name="foxglove drain", daemon=True)
        self._drainer.start()

    def _drain(self) -> None:
        priority.normal()  # never the bus loop's real-time priority
        while not self._stopping.wait(DRAIN_S):
            self.sink.drain()
        self.sink.drain()  # the stop frames, last

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        host = self.endpoint.host
        return f"ws://{f'[{host}]' if ':' in host else host}:{self.port}"

    def feed(self, recorder: GuardedRecorder | None, config: Config) -> LiveFeed:
        """What the bus pumps and the supervisor must feed for this view."""
        return live_feed(self.sink, recorder, config, self.watchers)

    def stop(self) -> None:
        self._stopping.set()
        self._drainer.join(STOP_S)
        # a viewer that stopped reading can hold the SDK's stop for as long as TCP keeps
        # its connection: never the way out (the drives are stopped already)
        stopping = threading.Thread(target=self.server.stop, name="foxglove stop", daemon=True)
        stopping.start()
        stopping.join(STOP_S)
        if stopping.is_alive():
            log.warning("foxglove: a viewer does not let go: its connection is left behind")
        sink = self.sink
        dropped = f", {sink.dropped} dropped (the live view fell behind)" if sink.dropped else ""
        log.info("foxglove: stopped; %d message(s) served%s", sink.served, dropped)


def start_foxglove(
    endpoint: Endpoint, name: str, schemas: Mapping[str, str] = SCHEMAS
) -> FoxgloveLive:
    """The server listening at ``endpoint``, or an :class:`Abh3Error` a user can act on
    (the port is taken, the host is not this machine's): before any bus opens."""
    check_installed(f"--foxglove {endpoint}")
    import foxglove

    # the SDK's own lines (a viewer connects, leaves, falls behind) in our log, named
    foxglove.set_log_level(logging.INFO)
    sdk = logging.getLogger("foxglove")
    if not any(isinstance(h, _SdkLines) for h in sdk.handlers):
        sdk.addHandler(_SdkLines())
        sdk.propagate = False  # said once, through ours
    context, watchers = foxglove.Context(), Watchers()
    try:
        # the SDK's threads start with the server: at normal priority, as their creator
        server = _at_normal_priority(
            lambda: foxglove.start_server(
                name=name,
                host=endpoint.host,
                port=endpoint.port,
                capabilities=[],  # watch only: no publishing, services or parameters
                context=context,
                server_listener=cast("ServerListener", watchers),  # the two it needs
                message_backlog_size=BACKLOG,
            )
        )
    except RuntimeError as exc:
        why = str(exc).removeprefix("FoxgloveError: ")
        raise Abh3Error(f"--foxglove {endpoint}: cannot serve: {why}") from exc
    live = FoxgloveLive(server, FoxgloveSink(context, schemas), endpoint, watchers)
    log.info(
        "foxglove: serving live on %s (Foxglove: Open connection → Foxglove WebSocket)",
        live.url,
    )
    if not endpoint.loopback:
        log.warning(
            "foxglove: %s is reachable from the network: anyone who reaches it sees the "
            "robot's data (it accepts no commands)",
            live.url,
        )
    return live


class _SdkLines(logging.Handler):
    """The SDK's lines (its loggers, ``foxglove.*``), said in our log as a viewer's doing:
    named, made printable and short (a viewer's text is in some: no forged lines, no
    terminal escapes), at most WARNING (a viewer's garbage or its going away is no error
    of ours), each said once in a row and at most ``SDK_LINES_PER_S`` a second, the rest
    counted into the next line said."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.clock = clock
        self.last, self.window, self.said, self.unsaid = "", -math.inf, 0, 0

    def emit(self, record: logging.LogRecord) -> None:
        text = "".join(c if c.isprintable() else "?" for c in record.getMessage())
        text = text[:SDK_LINE_CHARS]
        now = self.clock()
        if now >= self.window:
            self.window, self.said = now + 1.0, 0
        if text == self.last or self.said >= SDK_LINES_PER_S:
            self.unsaid += 1
            return
        self.last, self.said = text, self.said + 1
        more = f" ({self.unsaid} more not shown)" if self.unsaid else ""
        self.unsaid = 0
        log.log(min(record.levelno, logging.WARNING), "foxglove: %s%s", text, more)


def _at_normal_priority(start: Callable[[], T]) -> T:
    """``start()`` on a thread of normal priority (what it starts inherits it), even when
    called from the bus loop's real-time one."""
    with ThreadPoolExecutor(1, "foxglove start", initializer=priority.normal) as pool:
        return pool.submit(start).result()
