"""``--record run.mcap``: the raw CAN frames and the decoded values as ROS 2 messages.

An MCAP file with the ``ros2`` profile, CDR messages and ``ros2msg`` schemas, as rosbag2
writes it, so ``ros2 bag info/play``, Foxglove and rosbags open it. Its topics and their
messages are :class:`~.ros_topics.RosTopics`' (this file is one of its sinks): the raw
frames of every bus, each unit's feedback and status packets, each robot's odometry,
``/diagnostics``.

Written on the event loop as frames and events arrive. The chunk in progress is closed,
compressed and written at every :meth:`McapRecording.flush` (every ``FLUSH_S``, see
:mod:`.recorder`) or at ``CHUNK_BYTES``, whichever comes first, so a ``kill -9`` loses at
most the last ``FLUSH_S``. What it leaves has no summary (index, statistics, footer):
readers that go through the file from the start read it (the mcap library's
``StreamReader`` and ``NonSeekingReader``, ``abh3 decode``); those that seek to the
summary first need ``mcap recover`` to rewrite it. A write that fails (disk full) ends the
recording through :class:`~.recorder.GuardedRecorder`, never the run. ``mcap`` is imported
only here, only when an ``.mcap`` recording is asked for.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Generator
from pathlib import Path
from typing import IO, Any

import can

from abh3_supervisor.config.model import Config
from abh3_supervisor.core.supervisor import Supervisor
from abh3_supervisor.errors import BusOpenError, install_hint
from abh3_supervisor.runtime.mcap_index import spill_chunk_indexes
from abh3_supervisor.runtime.ros_topics import SCHEMAS, VENDOR, Captured, RosTopics

__all__ = ["CHUNK_BYTES", "VENDOR", "McapRecording", "open_mcap", "read_frames"]

CHUNK_BYTES = 256 << 10  # an upper bound: the flush closes a chunk sooner
INSTALL_HINT = install_hint("mcap")
LIBRARY = "abh3-supervisor"


def open_mcap(path: Path, config: Config) -> McapRecording:
    """The recording, or a BusOpenError a user can act on (before any bus opens)."""
    try:
        import mcap.writer  # noqa: F401  (only to say now if it is missing)
    except ImportError as exc:
        raise BusOpenError(
            f"--record {path}: an .mcap recording needs the mcap libraries: {INSTALL_HINT}"
            f" ({exc.name or exc} is not installed)"
        ) from exc
    try:
        stream = open(path, "wb")  # noqa: SIM115  (closed in stop())
    except OSError as exc:
        raise BusOpenError(f"--record {path}: cannot write: {exc.strerror}") from exc
    return McapRecording(stream, config, index_dir=path.parent)


class McapRecording(can.Listener):
    """The ``.mcap`` file: a :class:`~.ros_topics.TopicSink` fed by its own
    :class:`~.ros_topics.RosTopics` (:attr:`topics`, which other sinks may share), with the
    recorder's interface (a bus listener, ``attach``/``observe``, ``flush``/``stop``).

    A write that fails (disk full) breaks the file only: the file takes no more messages,
    the other sinks of :attr:`topics` get this one and the next, and the failure is raised
    once, after them, to whoever fed the frame or event — the
    :class:`~.recorder.GuardedRecorder`, which reports it and stops feeding this object.
    A sink that must outlive the file is therefore best fed by the runtime itself (its
    frames and events to :attr:`topics`), not only through the recorder."""

    def __init__(self, stream: IO[bytes], config: Config, index_dir: Path | None = None) -> None:
        from mcap.well_known import MessageEncoding, Profile, SchemaEncoding
        from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

        from abh3_supervisor.runtime.mcap_messages import fast_add  # imports mcap

        self.stream = stream
        self.writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self.writer.start(profile=Profile.ROS2, library=f"{LIBRARY_IDENTIFIER} {LIBRARY}")
        # what would grow with the length, on disk (None: kept by the writer, in memory)
        self.index = None if index_dir is None else spill_chunk_indexes(self.writer, index_dir)
        self.schemas = {
            name: self.writer.register_schema(name, SchemaEncoding.ROS2, text.encode())
            for name, text in SCHEMAS.items()
        }
        self._cdr = MessageEncoding.CDR
        self._add = fast_add(self.writer)
        self.channels: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.topics = RosTopics(config, [self])
        # on the loop: what of an event is recorded (the topics' own, no call in between)
        self.capture: Callable[[object], list[Captured]] = self.topics.capture
        self._finished = False
        self.broken = False
        self.error: Exception | None = None  # the write that failed, until raised

    def write(self, topic: str, schema: str, data: bytes, ns: int) -> None:
        """A message, on its topic's channel (made at its first), numbered per topic."""
        if self.broken:
            return
        self.counts[topic] = sequence = self.counts.get(topic, 0) + 1
        channel = self.channels.get(topic)
        try:
            if channel is None:
                channel = self.channels[topic] = self.writer.register_channel(
                    topic, self._cdr, self.schemas[schema]
                )
            self._add(channel, ns, data, sequence)
        except Exception as exc:  # kept, not raised into RosTopics: the other sinks go on
            self.broken = True  # disk full: what is on disk stays readable, nothing more
            self.error = exc

    def _raise_failure(self) -> None:
        """The failed write, once, for the recorder to report (after the other sinks)."""
        if self.error is not None:
            error, self.error = self.error, None
            raise error

    # ------------------------------------------------------------ the topics

    def on_message_received(self, msg: can.Message) -> None:
        self.topics.on_message_received(msg)
        self._raise_failure()

    def attach(self, sup: Supervisor, clock: Callable[[], float]) -> None:
        """Record ``sup``'s decoded values; ``clock`` is its clock (the loop's)."""
        self.topics.attach(sup, clock)

    def observe(self, event: object) -> None:
        """A supervisor event (on the loop thread), written at once."""
        self.topics.observe(event)
        self._raise_failure()

    def replay(self, item: Captured) -> None:
        """Write what :meth:`capture` took (the recorder's thread)."""
        self.topics.replay(item)
        self._raise_failure()

    # ------------------------------------------------------------ the end

    def flush(self) -> None:
        """Close the chunk in progress and hand the file's bytes to the OS."""
        if self._finished or self.broken:
            return
        mcap: Any = self.writer
        try:
            if hasattr(mcap, "flush"):  # recent mcap: closes the chunk, flushes the stream
                mcap.flush()
                return
            mcap._Writer__finalize_chunk()  # older mcap: the same, by its private name
            self.stream.flush()
        except Exception:
            self.broken = True  # as for a failed write: the whole chunks written stay
            raise

    def stop(self) -> None:
        """Index and close the file (after the stop frames)."""
        if self._finished:
            return
        self._finished = True
        try:
            if self.broken:  # after a failed write: keep the whole chunks already written
                with contextlib.suppress(OSError):
                    self.stream.close()
                return
            try:
                self.writer.finish()  # type: ignore[no-untyped-call]
            finally:
                self.stream.close()
        finally:
            if self.index is not None:
                self.index.close()  # unlinked already: closing frees its space


def read_frames(
    path: Path, say: Callable[[str], None]
) -> Generator[can.Message, None, tuple[int, int]]:
    """The raw frames of an MCAP recording, in order, up to where it breaks off: read as a
    stream from the start, it needs no summary (a ``kill -9`` or a full disk leaves none)."""
    try:
        from mcap.exceptions import EndOfFile
        from mcap.records import Channel, Message
        from mcap.stream_reader import StreamReader
    except ImportError as exc:
        raise BusOpenError(f"{path}: reading .mcap needs the mcap library: {INSTALL_HINT}") from exc
    read = 0
    channels: dict[int, str] = {}
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, skip_magic=False).records:
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    topic = channels.get(rec.channel_id, "")
                    if topic.startswith("/can/"):
                        read += 1
                        yield _frame(rec.data, topic)
        except EndOfFile:  # no summary and footer: the recording did not end normally
            say(
                f"{path}: the file breaks off after frame {read}, without the summary a finished"
                " recording has (killed, or the disk filled): read up to there"
            )
            return read, 1
        except Exception as exc:  # damaged
            say(f"{path}: cannot read past frame {read} ({str(exc) or type(exc).__name__})")
            return read, 1
    return read, 0


def _frame(cdr: bytes, topic: str) -> can.Message:
    """can_msgs/Frame from its CDR bytes: the header's string sets where the rest starts."""
    import struct

    sec, nanosec, length = struct.unpack_from("<iII", cdr, 4)
    at = 4 + 12 + length
    at += -(at - 4) % 4  # uint32 id aligned to 4 from the start of the data
    ident, rtr, extended, error, dlc = struct.unpack_from("<I???B", cdr, at)
    data = cdr[at + 8 : at + 16]
    return can.Message(
        timestamp=sec + nanosec / 1e9,
        arbitration_id=ident,
        is_extended_id=extended,
        is_remote_frame=rtr,
        is_error_frame=error,
        is_rx=topic.endswith("/rx"),
        dlc=dlc,
        data=data[:dlc],
        channel=topic.split("/")[2],
    )
