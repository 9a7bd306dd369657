"""``--foxglove [HOST:]PORT``: the MCAP recording's topics, live, over the Foxglove
WebSocket protocol, served by a server of our own (:mod:`.foxglove_server`), without ROS.

The same CDR messages and ``ros2msg`` schemas the recording writes (they come from the
one producer, :mod:`.ros_topics`), one channel per topic, made the first time the topic
is written. The server accepts no commands: it advertises no capability (no client
publishing, services or parameters), so a viewer can only watch.

A slow or absent viewer costs the bus nothing. Without an ``.mcap`` recording, the
high-rate topics (frames, feedback) are not even produced while no viewer subscribes
(:class:`LiveFeed`). :meth:`FoxgloveSink.write`, on the bus loop (or the recorder's
writer thread), only appends the message to a bounded queue — nothing at all for a topic
no viewer subscribes to — and the server's thread, at normal priority, takes the queue
every ``DRAIN_S`` and hands each message to the queue of each viewer subscribed to it. A
full hand-off queue (that thread starved) drops the message, counts it and says so once.
Each viewer's own queue (``foxglove_server.BACKLOG``) drops its oldest message when the
viewer falls behind, counted per viewer (:attr:`FoxgloveLive.viewers`) and said in the
log. ``websockets`` is imported only when a server starts (the ``foxglove`` extra).
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Mapping

import can

from abh3_supervisor.config.endpoint import Endpoint
from abh3_supervisor.config.model import Config
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import Abh3Error, install_hint
from abh3_supervisor.runtime.foxglove_server import (
    SUBPROTOCOL,
    Channel,
    FoxgloveServer,
    Watchers,
    bind_error,
)
from abh3_supervisor.runtime.recorder import GuardedRecorder
from abh3_supervisor.runtime.ros_topics import SCHEMAS, RosTopics, TopicSink
from abh3_supervisor.scheduler.core import FeedbackEvent

__all__ = ["SUBPROTOCOL", "FoxgloveLive", "FoxgloveSink", "LiveFeed", "Watchers"]
log = logging.getLogger(__name__)
INSTALL_HINT = install_hint("foxglove")
QUEUE = 8192  # messages waiting for the server's thread: ~8 s of 4 units at 100 Hz
DRAIN_S = 0.02  # the live view's added latency; 50 wake-ups a second, not one a message
STOP_S = 1.0  # what the stop gives the viewers to take what is queued for them


def check_installed(option: str) -> None:
    """Say now, before anything opens, that the extra is missing (exit 2)."""
    try:
        import websockets  # noqa: F401
    except ImportError as exc:
        raise Abh3Error(
            f"{option}: live view in Foxglove needs websockets: {INSTALL_HINT}"
            f" ({exc.name or exc} is not installed)"
        ) from exc


Message = tuple[str, str, bytes, int]  # topic, schema, CDR bytes, wall-clock ns
Publish = Callable[[str, str, bytes, int], None]


class FoxgloveSink:
    """A :class:`~.ros_topics.TopicSink`: each topic's CDR messages queued on the bus
    loop and handed, by :meth:`drain` on the server's thread, to ``publish`` (the
    server's: to each viewer subscribed to the topic's channel)."""

    def __init__(self, channels: Mapping[str, Channel], publish: Publish) -> None:
        self.channels = channels  # topic → its channel, once made (the server's)
        self.publish = publish
        self.queue: collections.deque[Message] = collections.deque()
        self.served = 0  # messages handed to the server (each viewer gets them, or drops)
        self.dropped = 0  # messages the full queue turned away (on the loop)
        self.failed = 0  # messages the server refused (said once)

    def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        """On the bus loop: never blocks, never raises, never does a viewer's work."""
        channel = self.channels.get(topic)
        # until its channel is made, every message of the topic is queued (a channel
        # must exist to be advertised, and a viewer must see it to subscribe)
        if channel is not None and not channel.subscriptions:
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
        """Hand what is queued to the server (on its thread)."""
        queue, publish = self.queue, self.publish
        while queue:
            topic, schema, data, ns = queue.popleft()
            try:
                publish(topic, schema, data, ns)
            except Exception as exc:  # a viewer's trouble is never the bus's
                self.failed += 1
                if self.failed == 1:
                    log.error(
                        "foxglove: %s: not served (%r); the drives are unaffected", topic, exc
                    )
                continue
            self.served += 1


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
    """The server and the sink that feeds it; :meth:`stop` ends both."""

    def __init__(self, server: FoxgloveServer, sink: FoxgloveSink, endpoint: Endpoint) -> None:
        self.server, self.sink, self.endpoint = server, sink, endpoint
        self.watchers = server.watchers
        self._stopped = False

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def url(self) -> str:
        host = self.endpoint.host
        return f"ws://{f'[{host}]' if ':' in host else host}:{self.port}"

    @property
    def viewers(self) -> dict[str, tuple[int, int]]:
        """Each viewer (``#N host:port``, connected or gone): (messages sent to it,
        messages it missed: dropped by its full queue, or left queued at the stop)."""
        return self.server.viewers

    def feed(self, recorder: GuardedRecorder | None, config: Config) -> LiveFeed:
        """What the bus pumps and the supervisor must feed for this view."""
        return live_feed(self.sink, recorder, config, self.watchers)

    def stop(self) -> None:
        """The stop frames to the viewers, ``STOP_S`` for each to take what is queued
        for it (one that does not is cut), then each viewer's count in the log."""
        if self._stopped:
            return
        self._stopped = True
        # the server's thread is never the way out's (the drives are stopped already)
        if not self.server.stop(3 * STOP_S):
            log.warning("foxglove: a viewer does not let go: the server is left behind")
        for name, (sent, missed) in self.viewers.items():
            if missed:
                log.warning(
                    "foxglove: viewer %s missed %d of %d message(s)", name, missed, sent + missed
                )
        sink = self.sink
        dropped = f", {sink.dropped} dropped (the live view fell behind)" if sink.dropped else ""
        log.info(
            "foxglove: stopped; %d message(s) handed to the server for its viewers%s",
            sink.served,
            dropped,
        )


def start_foxglove(
    endpoint: Endpoint, name: str, schemas: Mapping[str, str] = SCHEMAS
) -> FoxgloveLive:
    """The server listening at ``endpoint``, or an :class:`Abh3Error` a user can act on
    (the port is taken, the host is not this machine's): before any bus opens."""
    check_installed(f"--foxglove {endpoint}")
    server = FoxgloveServer(name, endpoint.host, endpoint.port, schemas, STOP_S)
    sink = FoxgloveSink(server.channels, server.publish)
    try:
        server.start(lambda: sink.drain(), DRAIN_S)  # sink.drain as it is then
    except OSError as exc:
        why = bind_error(exc, endpoint.host, endpoint.port)
        raise Abh3Error(
            f"{endpoint.where} {endpoint}: cannot serve: {why}; give another port "
            "(0: any free one, the log names it)"
        ) from exc
    live = FoxgloveLive(server, sink, endpoint)
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
