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
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import can

from abh3_supervisor.config.model import Config
from abh3_supervisor.errors import Abh3Error, BusOpenError

log = logging.getLogger(__name__)
FLUSH_S = 0.5  # what a kill -9 may lose at most (docs/recording.md promises ≤ 1 s)


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
    :meth:`start_flushing` flushes it every ``FLUSH_S`` on the loop. Frames (the pumps),
    events (the supervisor) and flushes all come on the loop thread, one at a time."""

    def __init__(self, path: Path, writer: can.Listener) -> None:
        self.path, self.writer = path, writer
        self.failed: str | None = None
        self.failed_at: float | None = None  # wall clock of the failure
        self._timer: asyncio.TimerHandle | None = None
        self._stopped = False

    def on_message_received(self, msg: can.Message) -> None:
        if self.failed is not None or self._stopped:
            return
        try:
            self.writer.on_message_received(msg)
        except Exception as exc:
            self._fail("writing", exc)

    def observe(self, event: object) -> None:
        """A supervisor event, for writers that record decoded values too (MCAP)."""
        if self.failed is not None or self._stopped:
            return
        try:
            self.writer.observe(event)  # type: ignore[attr-defined]
        except Exception as exc:
            self._fail("writing", exc)

    def flush(self) -> None:
        if self.failed is not None or self._stopped:
            return
        try:
            _flush(self.writer)
        except Exception as exc:
            self._fail("writing", exc)

    def start_flushing(self, loop: asyncio.AbstractEventLoop) -> None:
        """Flush now (the file's header reaches the disk) and every ``FLUSH_S`` on
        ``loop``, on a fixed grid, until :meth:`stop`."""
        self.flush()
        self._tick(loop, loop.time())

    def _tick(self, loop: asyncio.AbstractEventLoop, at: float) -> None:
        if self._stopped:
            return
        at = max(at + FLUSH_S, loop.time())  # a late tick does not bunch the next ones
        self._timer = loop.call_at(at, self._flush_and_repeat, loop, at)

    def _flush_and_repeat(self, loop: asyncio.AbstractEventLoop, at: float) -> None:
        self.flush()
        self._tick(loop, at)

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
        if self._timer is not None:
            self._timer.cancel()
        if self._stopped:
            return
        self._stopped = True
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
