"""The MCAP file as the recorder's writer thread sees it: open, write ticks, sync points, close.

Crash safety comes from MCAP's chunks. Messages go into the open chunk in memory; a *sync point* ends that
chunk (compressed, with its message indexes), hands it to the OS and, with ``fsync``, flushes it to the
device. A reader that finds no summary at the end of the file (the process was killed) reads the data section
record by record and stops at the first torn record (:func:`~.reader.read_mcap`), so a ``kill -9`` loses at
most the open chunk: the records since the last sync point (``sync_interval_s``, 1 s by default). A closed
file has the summary and opens with any MCAP tool.

A full disk. The ``mcap`` writer writes into a :class:`_Spool` (memory), and a sync point writes the spool to
the file all or nothing: before writing it reserves the blocks (``fallocate`` keeping the file's size, on
Linux), so a full disk is found before a byte is written; where reserving is not possible a write that fails
half way is cut back to the end of the last complete record. Either way the file always ends at a record
boundary, the chunk stays in memory and the next sync point retries it at the same offset (the offsets the
``mcap`` writer recorded for its indexes stay true), and recording goes on once space is back. Each
reservation also keeps room for a short ending (``DataEnd`` and a ``Footer`` without summary) behind the data,
so a file closed on a full disk still ends cleanly: readers read it linearly to its end; only its summary
(the index) and the ticks of the chunk that never got in are missing, the latter counted in :attr:`lost`.
Where nothing can be reserved, that room is taken by writing the short ending itself behind the data at each
sync point (the next one writes over it): the file then ends cleanly at every moment, after a ``kill -9`` too,
and a write that fails half way is cut back to the data and that ending, written again in place (no new room).

Records. Every message of one record (a tick, or a tub record converted) carries the record's number, from 1,
in MCAP's per-message ``sequence`` field, so a reader groups a record's messages by it
(:class:`~.reader.McapTub`) rather than by log time, which two records may share (a tub stamps whole
milliseconds).
"""

from __future__ import annotations

import ctypes
import errno
import logging
import os
from collections.abc import Callable
from typing import IO, Any

from ...clock._libc import libc_function
from ...extras import require
from ..tub.fileio import with_filename
from .encode import ChannelSpec, TickEncoder, TickSnapshot, TimeMap

__all__ = ["CLOCK_METADATA", "McapSink"]

logger = logging.getLogger(__name__)

#: name of the metadata record holding the :class:`~.encode.TimeMap` anchor
CLOCK_METADATA = "asyncdonkey.clock"
#: name of the metadata record holding the recording's description (channels asked for, rate, user metadata)
SESSION_METADATA = "asyncdonkey.session"
PROFILE = ""

_FALLOC_FL_KEEP_SIZE = 1
_OFF_T = (ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64)
#: ``fallocate`` with 64-bit offsets: ``fallocate64`` (glibc, every architecture), else ``fallocate`` where
#: ``off_t`` is 64 bits wide anyway
_FALLOCATE = libc_function("fallocate64", _OFF_T) or (
    libc_function("fallocate", _OFF_T) if ctypes.sizeof(ctypes.c_long) == 8 else None
)


def _short_ending() -> bytes:
    """``DataEnd``, a ``Footer`` naming no summary, and the closing magic: the least that ends an MCAP file
    cleanly (a reader reads its data section to the footer; tools without an index read it linearly)."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import DataEnd, Footer
    from mcap.writer import MCAP0_MAGIC

    builder = RecordBuilder()
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return builder.end() + MCAP0_MAGIC


class _Spool:
    """The bytes the ``mcap`` writer produces, kept in memory until :meth:`commit` writes them to the file.

    ``write``/``tell``/``flush`` are what the writer needs of a stream (``tell`` counts committed and pending
    bytes, so the offsets it records are the ones the bytes will have in the file). :meth:`commit` writes the
    pending bytes all or none, see the module docstring.
    """

    def __init__(self, file: IO[bytes], path: str, ending: bytes) -> None:
        self._file = file
        self._path = path
        self._ending = ending
        self._pending = bytearray()
        self.committed = 0
        """bytes in the file, all of them whole records"""
        self.ends_cleanly = False
        """the file holds the short ending right after the committed records (written where no blocks can be
        reserved, see :meth:`commit`)"""
        self._can_reserve = _FALLOCATE is not None

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        return self.committed + len(self._pending)

    def flush(self) -> None:
        """Nothing: the bytes go to the file at :meth:`commit` only."""

    @property
    def pending(self) -> int:
        return len(self._pending)

    def commit(self, keep_end_reserve: bool = True) -> None:
        """Write the pending bytes at the end of the file: all of them, or (raising ``OSError`` naming the
        file) none, the file then still ending after the last complete record."""
        if not self._pending:
            return
        data = bytes(self._pending)
        room = len(self._ending) if keep_end_reserve else 0
        reserved = self._reserve(len(data) + room)
        # nothing reserved: the room for the ending is taken by writing it, behind the data (overwritten next time)
        tail = self._ending if room and not reserved else b""
        try:
            self._write_at(self.committed, data + tail)
            if self.ends_cleanly and len(data) + len(tail) < len(self._ending):
                self._file.truncate(self.committed + len(data) + len(tail))  # the old ending's last bytes
        except OSError as exc:
            self._cut_back()
            raise with_filename(exc, self._path) from exc
        self.committed += len(data)
        self.ends_cleanly = bool(tail)
        self._pending.clear()

    def _write_at(self, offset: int, data: bytes) -> None:
        f = self._file
        f.seek(offset)
        view = memoryview(data)
        while view:
            n = f.write(view)
            if not n:
                raise OSError(errno.EIO, "write made no progress")
            view = view[n:]
        f.flush()

    def discard(self) -> int:
        """Forget the pending bytes; returns how many there were."""
        n = len(self._pending)
        self._pending.clear()
        return n

    def _reserve(self, length: int) -> bool:
        """Allocate ``length`` bytes after the committed end without changing the file's size, so that writing
        them cannot fail for want of space; True when done. Raises ``OSError(ENOSPC)`` on a full disk, before
        anything is written; False where the OS or the file system cannot (the write then finds out)."""
        if not self._can_reserve or _FALLOCATE is None:
            return False
        if _FALLOCATE(self._file.fileno(), _FALLOC_FL_KEEP_SIZE, self.committed, length) == 0:
            return True
        err = ctypes.get_errno()
        if err in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL, errno.ENODEV):
            self._can_reserve = False  # a file system without it (or not a regular file): write and see
            return False
        raise OSError(err, os.strerror(err), self._path)

    def _cut_back(self) -> None:
        """Remove a partial write, so the file ends after its last complete record again, and with the short
        ending behind it if it had one: written again over the partial bytes, in place, where the old ending
        was (it needs no new room)."""
        f = self._file
        if self.ends_cleanly:
            try:
                self._write_at(self.committed, self._ending)
                f.truncate(self.committed + len(self._ending))
                return
            except OSError:
                self.ends_cleanly = False
        try:
            f.truncate(self.committed)
            f.seek(self.committed)
        except OSError as exc:  # pragma: no cover - truncating frees space, it does not need any
            logger.error("%s: could not cut off a partial write: %r", self._path, exc)


class McapSink:
    """One MCAP file, written from one thread.

    Args:
        path: the file (created or truncated).
        encoder: turns ticks into messages.
        metadata: string key/values saved as the ``asyncdonkey.session`` metadata record.
        fsync: flush to the device at sync points.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        chunk_size: bytes after which a chunk is ended even between sync points (and a sync point asked for).
        open_file: opens the file, unbuffered (tests pass one that fails like a full disk).

    Raises ``OSError`` when the file cannot be created with its header (a disk already full).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        encoder: TickEncoder,
        *,
        metadata: dict[str, str] | None = None,
        fsync: bool = True,
        compression: str = "zstd",
        chunk_size: int = 4 * 1024 * 1024,
        open_file: Callable[[str], IO[bytes]] | None = None,
    ) -> None:
        require("mcap", "mcap", "recording MCAP files")
        require("foxglove", "mcap", "recording MCAP files")  # the encoder's image and scan schemas
        from mcap.writer import CompressionType, Writer

        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in comp:
            raise ValueError(f"McapRecorder({path}): compression must be one of {sorted(comp)}, got {compression!r}")
        self.path = os.fspath(path)
        self.encoder = encoder
        self.fsync = fsync
        self._chunk_size = chunk_size
        self._ending = _short_ending()
        self._file: IO[bytes] = (open_file or _open)(self.path)
        self._spool = _Spool(self._file, self.path, self._ending)
        self._writer = Writer(self._spool, chunk_size=chunk_size, compression=comp[compression])  # type: ignore[arg-type]
        self._writer.start(profile=PROFILE, library="asyncdonkey")
        try:
            self._spool.commit()
        except OSError:
            self._file.close()
            raise
        self._metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        self.times: TimeMap | None = None
        """set by the recorder before it queues the first tick"""
        self._anchored = False
        self._closed = False
        # counters read by BackgroundWriter.stats
        self.unsynced = 0
        self.sync_requested = False
        self.durable = 0
        self.syncs = 0
        self.messages = 0
        self.lost = 0
        """ticks :meth:`write` took whose chunk never reached the file (the disk was full at :meth:`close`)"""
        self._written = 0
        self._in_file = 0  # ticks whose chunk is in the file (committed), durable or not

    @property
    def bad_values(self) -> int:
        return self.encoder.bad_values

    def _channel(self, spec: ChannelSpec) -> int:
        cid = self._channels.get(spec.topic)
        if cid is None:
            key = (spec.schema_name, spec.schema_encoding, spec.schema_data)
            sid = self._schemas.get(key)
            if sid is None:
                sid = self._schemas[key] = self._writer.register_schema(
                    spec.schema_name, spec.schema_encoding, spec.schema_data
                )
            cid = self._channels[spec.topic] = self._writer.register_channel(spec.topic, spec.message_encoding, sid)
        return cid

    def write(self, t: float, payload: tuple[Any, ...]) -> None:
        """Add one tick's messages (a :class:`~.encode.TickSnapshot` as a tuple) to the open chunk (memory; the
        file is written at sync points)."""
        snap = TickSnapshot(*payload)
        times = self.times
        if times is None:  # pragma: no cover - the recorder sets it before queueing
            raise RuntimeError(f"{self.path}: no time anchor")
        w = self._writer
        if not self._anchored:
            w.add_metadata(CLOCK_METADATA, times.as_metadata())
            if self._metadata:
                w.add_metadata(SESSION_METADATA, self._metadata)
            self._anchored = True
        seq = _sequence(self._written + 1)
        for spec, data, log_ns, pub_ns in self.encoder.encode(snap, times):
            w.add_message(self._channel(spec), log_ns, data, pub_ns, seq)
            self.messages += 1
        self._written += 1
        self.unsynced += 1
        if self._spool.pending >= self._chunk_size:
            self.sync_requested = True  # a chunk ended by size: write it out rather than hold it in memory

    def write_timing(self, payload: tuple[Any, ...]) -> None:
        """Add the timing due at ``payload`` (a :class:`~.encode.TickSnapshot` without values) to the open chunk,
        as part of the last record: the recorder's last word at shutdown, the last tick's figures and the samples
        taken after its last run."""
        times = self.times
        if times is None or self._closed:
            return
        seq = _sequence(max(1, self._written))
        for spec, data, log_ns, pub_ns in self.encoder.timing_messages(TickSnapshot(*payload), times):
            self._writer.add_message(self._channel(spec), log_ns, data, pub_ns, seq)
            self.messages += 1

    def sync(self) -> bool:
        """End the open chunk and write it to the file, then (with ``fsync``) to the device.

        Raises ``OSError`` naming the file when the disk has no room (nothing of the chunk is then in the file;
        it is kept and the next sync point retries it) or the flush fails.
        """
        self.sync_requested = False
        if not self.unsynced:
            return False
        self._writer.flush()  # ends the chunk into the spool: memory only
        self._spool.commit()
        self._in_file = self._written
        if self.fsync:
            try:
                os.fsync(self._file.fileno())
            except OSError as exc:
                raise with_filename(exc, self.path) from exc
        self.unsynced = 0
        self.durable = self._written
        self.syncs += 1
        return True

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close. Safe to call twice.

        On a full disk the ticks not yet in the file are counted in :attr:`lost`, the file gets the short
        ending instead (see the module docstring) and ``OSError`` says what happened.
        """
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()  # ends the open chunk and adds the summary and footer, into the spool
            try:
                self._spool.commit(keep_end_reserve=False)
            except OSError as exc:
                raise self._close_short(exc) from exc
            self._in_file = self.durable = self._written
            self.unsynced = 0
            if self.fsync:
                os.fsync(self._file.fileno())
        finally:
            try:
                self._file.close()
            except OSError as exc:
                logger.error("%s: closing failed: %r", self.path, exc)

    def _close_short(self, exc: OSError) -> OSError:
        """The disk has no room for the rest: end the file after its last complete chunk; returns the error to
        raise, which says how many ticks are lost and how the file ends."""
        spool = self._spool
        spool.discard()
        self.lost = self._written - self._in_file
        self.unsynced = 0
        how = "it ends after its last complete chunk, without a summary (readers read it linearly)"
        if not spool.ends_cleanly:  # else the ending is there already, behind the last chunk
            spool.write(self._ending)
            try:
                spool.commit(keep_end_reserve=False)
                if self.fsync:
                    os.fsync(self._file.fileno())
            except OSError:
                spool.discard()
                how = "it ends after its last complete chunk, without a footer (readers stop there)"
        return OSError(exc.errno, f"{exc.strerror or exc}: {self.lost} ticks not written; {how}", self.path)


def _open(path: str) -> IO[bytes]:
    """Create the file, and its directory as the tub writer does (``--mcap runs/today/drive.mcap`` just works)."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    return open(path, "wb", buffering=0)


def _sequence(record: int) -> int:
    """Record number ``record`` (from 1) as MCAP's uint32 ``sequence``; after 2**32 - 1 records (six years at
    20 Hz) it wraps to 1, never to 0, which marks files written without record numbers."""
    return (record - 1) % 0xFFFFFFFF + 1
