"""``--record``'s writer: python-can's formats and MCAP, flushed every ``FLUSH_S``, and
guarded so that a failing disk ends the recording, never the run.

What a ``kill -9`` leaves: everything up to the last flush, at most ``FLUSH_S`` old. The
text formats (``.log``, ``.asc``, ``.csv``) reach the file only at a flush, in whole
lines (:class:`WholeLines`), so a kill never leaves half a line; ``.blf`` writes its log
container and brings the file header up to date at each flush (:class:`FlushedBLFWriter`),
so the file read back is a complete BLF file; ``.mcap`` closes its chunk at each flush
(:meth:`.McapRecording.flush`): the file lacks only the summary written at the end.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from collections import deque
from datetime import datetime
from pathlib import Path
from typing import Any

import can

from abh3_supervisor.config.model import Config
from abh3_supervisor.errors import Abh3Error, BusOpenError

log = logging.getLogger(__name__)
FLUSH_S = 0.5  # what a kill -9 may lose at most (docs/recording.md promises ≤ 1 s)
WRITE_S = 0.1  # the writer's thread writes what waits this often
QUEUE_SIZE = 50_000  # frames and events waiting for the writer: about a minute of 4
# units at 100 Hz with their status polls (a stalled disk), then counted and dropped


class ASCWriter(can.ASCWriter):
    """python-can's ASC writer, with the milliseconds of its header's dates in three digits:
    python-can 4.6 writes 24 ms as ``.24``, which its own reader takes for 240 ms, so the
    absolute time of every frame was off by up to 0.9 s."""

    def _format_header_datetime(self, dt: datetime) -> str:
        return dt.strftime(f"%a %b %d %H:%M:%S.{dt.microsecond // 1000:03d} %Y")


TEXT_WRITERS: dict[str, type[can.io.generic.TextIOMessageWriter]] = {
    ".log": can.CanutilsLogWriter,
    ".asc": ASCWriter,
    ".csv": can.CSVWriter,
}


class WholeLines:
    """The text file a python-can writer writes to, reaching the disk only at
    :meth:`flush`: called between messages, so the file holds whole lines only. A write
    that fails part-way (disk full) is cut back to the last flush, and raised."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = open(path, "wb", buffering=0)  # noqa: SIM115  (closed in close())
        self._parts: list[str] = []
        self._pending = 0  # characters not yet written (ASCII in every format)
        self.size = 0  # bytes on disk, whole lines

    def write(self, text: str) -> int:
        self._parts.append(text)
        self._pending += len(text)
        return len(text)

    def flush(self) -> None:
        if not self._parts:
            return
        data = "".join(self._parts).encode("utf-8")
        self._parts.clear()
        self._pending = 0
        written = 0
        try:
            while written < len(data):
                written += self._file.write(data[written:]) or 0
        except OSError:
            with contextlib.suppress(OSError):  # back to the last whole line
                os.ftruncate(self._file.fileno(), self.size)
                self._file.seek(self.size)
            raise
        self.size += len(data)

    def tell(self) -> int:  # python-can's file_size()
        return self.size + self._pending

    @property
    def closed(self) -> bool:
        return self._file.closed

    def close(self) -> None:
        if self._file.closed:
            return
        try:
            self.flush()
        finally:
            self._file.close()


class FlushedBLFWriter(can.BLFWriter):
    """python-can's BLF writer, whose compressed log container is written out at every
    :meth:`flush` (not only when 128 KiB of frames have gathered), with the file header
    brought up to date (start time, object count), as ``stop()`` does at the end: after a
    kill, python-can's BLFReader reads the file as it stood at the last flush, absolute
    timestamps included."""

    def flush(self) -> None:
        if self.file.closed:
            return
        while self._buffer_size > 0:  # private: python-can's container writer
            self._flush()
        end = self.file.tell()
        self.file.seek(0)
        self._write_header(end)
        self.file.seek(end)
        self.file.flush()


OURS = (".log", ".asc", ".blf", ".csv", ".mcap")  # flushed for a kill -9 (above)
GZIPPED = (".log", ".asc", ".csv", ".trc", ".txt")  # python-can compresses these as .gz


def known_formats() -> str:
    others = sorted(set(can.io.logger.MESSAGE_WRITERS) - set(OURS))
    return f"{' '.join(OURS)}, or python-can's {' '.join(others)} (text ones also .gz)"


def check_format(path: Path) -> None:
    """``--record`` names a format we can write, in a folder that takes it: asked before
    anything opens (a bus, a file), so a typo is exit 2 with nothing started
    (:class:`Abh3Error`)."""
    suffixes = [s.lower() for s in path.suffixes[-2:]]
    suffix = suffixes[-1] if suffixes else ""
    known = suffix in OURS or suffix in can.io.logger.MESSAGE_WRITERS
    if not known and not (suffix == ".gz" and len(suffixes) == 2 and suffixes[0] in GZIPPED):
        said = f"'{suffix}'" if suffix else "no extension"
        raise Abh3Error(f"--record {path}: {said} is not a recording format; use {known_formats()}")
    folder = path.parent
    if not folder.is_dir():
        raise Abh3Error(f"--record {path}: cannot write: there is no folder {folder}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise Abh3Error(f"--record {path}: cannot write: {folder}: permission denied")


def _writer(path: Path) -> can.Listener:
    """python-can's writer for the file's extension (ValueError: no such format)."""
    suffix = path.suffix.lower()
    if suffix in TEXT_WRITERS:
        return TEXT_WRITERS[suffix](WholeLines(path))  # type: ignore[arg-type]
    if suffix == ".blf":
        return FlushedBLFWriter(path)
    return can.Logger(str(path))  # another format python-can knows: its own buffering


def _flush(writer: Any) -> None:
    """Out to the OS (page cache: survives the process, not a power cut — no fsync)."""
    flush = getattr(writer, "flush", None)
    if flush is None:
        file = getattr(writer, "file", None)
        flush = getattr(file, "flush", None)
    if callable(flush):
        flush()


class GuardedRecorder(can.Listener):
    """``--record``'s writer, which may fail (disk full) without touching the bus path:
    the first failure is reported once, recording stops, the drives go on being driven.

    The loop only hands over: each frame (the pumps) and what each supervisor event
    leaves for the file (the writer's ``capture``, MCAP's decoded values) is appended to
    a queue, bounded by ``QUEUE_SIZE`` (what a starved writer cannot take is counted
    and said, in the log and at the end). Once :meth:`start_flushing` is called a thread
    of its own writes the queue every ``WRITE_S`` and hands the file to the OS every
    ``FLUSH_S``; before it (a test, a tool) :meth:`flush` and :meth:`stop` write what
    waits themselves. Writes happen under one lock, in the order they were handed over."""

    def __init__(self, path: Path, writer: can.Listener) -> None:
        self.path, self.writer = path, writer
        self.failed: str | None = None
        self.failed_at: float | None = None  # wall clock of the failure
        self.dropped = 0  # frames and events the full queue turned away
        self._queue: deque[Any] = deque()
        self._capture = getattr(writer, "capture", None)  # run on the loop per event
        self._replay = getattr(writer, "replay", None)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._ending = threading.Event()
        self._stopped = False

    def _taking(self) -> bool:
        """Whether frames and events are still queued: until a failure, or after it for
        a writer whose topics other sinks share (MCAP's, with a live view: its file
        takes nothing more, the view goes on through it)."""
        if self._stopped:
            return False
        if self.failed is None:
            return True
        topics = getattr(self.writer, "topics", None)
        return len(getattr(topics, "sinks", ())) > 1

    def on_message_received(self, msg: can.Message) -> None:
        """On the loop: queued, never written here."""
        if (self.failed is None and not self._stopped) or self._taking():
            if len(self._queue) < QUEUE_SIZE:
                self._queue.append(msg)
            else:
                self._drop()

    def observe(self, event: object) -> None:
        """A supervisor event, for writers that record decoded values too (MCAP): on the
        loop, what the writer needs of it is taken now and queued."""
        capture = self._capture
        if capture is None or ((self.failed is not None or self._stopped) and not self._taking()):
            return
        try:
            items = capture(event)
        except Exception as exc:
            self._fail("writing", exc)
            return
        for item in items:
            if len(self._queue) < QUEUE_SIZE:
                self._queue.append(item)
            else:
                self._drop()

    def _drop(self) -> None:
        self.dropped += 1
        if self.dropped in (1, 1000, 1_000_000):
            log.warning(
                "--record %s: the writer falls behind: %d frame(s) or event(s) not recorded",
                self.path,
                self.dropped,
            )

    def _write_waiting(self) -> None:
        """What the queue holds, to the writer (under the lock)."""
        queue, write, replay = self._queue, self.writer.on_message_received, self._replay
        while self.failed is None or self._taking():
            try:
                item = queue.popleft()
            except IndexError:
                return
            try:
                if isinstance(item, can.Message):
                    write(item)
                elif replay is not None:
                    replay(item)
            except Exception as exc:
                if self.failed is None:
                    self._fail("writing", exc)
        queue.clear()  # failed: what waits is not recorded

    def flush(self) -> None:
        """Write what waits and hand the file to the OS."""
        with self._lock:
            self._write_waiting()
            if self.failed is not None or self._stopped:
                return
            try:
                _flush(self.writer)
            except Exception as exc:
                self._fail("writing", exc)

    def start_flushing(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Flush now (the file's header reaches the disk), then write on a thread of its
        own every ``WRITE_S`` and flush every ``FLUSH_S``, until :meth:`stop`. (``loop``:
        unused, kept for callers.)"""
        self.flush()
        if self._thread is None and not self._stopped:
            self._thread = threading.Thread(
                target=self._run, name=f"record {self.path.name}", daemon=True
            )
            self._thread.start()

    def _run(self) -> None:
        flush_at = time.monotonic() + FLUSH_S
        while not self._ending.wait(WRITE_S):
            if time.monotonic() >= flush_at:
                flush_at += FLUSH_S
                self.flush()
            else:
                with self._lock:
                    self._write_waiting()

    def _fail(self, doing: str, exc: Exception) -> None:
        self.failed = str(exc)
        self.failed_at = time.time()
        log.error(
            "--record %s: %s failed (%s): the recording ends here; the drives are unaffected",
            self.path,
            doing,
            exc,
        )

    def stop(self) -> None:
        """Write what waits and close the file (the thread first ends)."""
        self._ending.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._lock:
            if self._stopped:
                return
            self._write_waiting()
            self._stopped = True
            if self.dropped:
                log.warning(
                    "--record %s: %d frame(s) or event(s) were not recorded: the writer "
                    "fell behind",
                    self.path,
                    self.dropped,
                )
            try:
                self.writer.stop()  # flushes and closes the file
            except Exception as exc:
                if self.failed is None:  # a writer that failed already says why once
                    self._fail("closing", exc)


def open_recorder(path: Path, config: Config | None = None) -> GuardedRecorder:
    if path.suffix.lower() == ".mcap" and config is not None:
        # imported here: the mcap libraries are an extra, loaded only when asked for
        from abh3_supervisor.runtime.mcap_recording import open_mcap

        return GuardedRecorder(path, open_mcap(path, config))
    try:
        writer = _writer(path)
    except ValueError as exc:
        raise BusOpenError(f"--record {path}: {exc} (use {known_formats()})") from exc
    except OSError as exc:
        raise BusOpenError(f"--record {path}: cannot write: {exc.strerror}") from exc
    return GuardedRecorder(path, writer)
