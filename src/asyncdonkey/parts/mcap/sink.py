"""The MCAP file as the recorder's writer thread sees it: open, write ticks, sync points, close.

Crash safety comes from MCAP's chunks. Messages go into the open chunk in memory; a *sync point* ends that
chunk (compressed, with its message indexes), hands it to the OS and, with ``fsync``, flushes it to the
device. A reader that finds no summary at the end of the file (the process was killed) reads the data section
record by record and stops at the first torn record (:func:`~.reader.read_mcap`), so a ``kill -9`` loses at
most the open chunk: the records since the last sync point (``sync_interval_s``, 1 s by default). A closed
file has the summary and opens with any MCAP tool.

After a write error (a full disk) the file ends at the last complete chunk, possibly followed by a torn one;
the sink stops writing (every later record counts as failed) instead of appending after a hole.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import IO, Any

from .encode import ChannelSpec, TickEncoder, TickSnapshot, TimeMap

__all__ = ["CLOCK_METADATA", "McapSink"]

logger = logging.getLogger(__name__)

#: name of the metadata record holding the :class:`~.encode.TimeMap` anchor
CLOCK_METADATA = "asyncdonkey.clock"
#: name of the metadata record holding the recording's description (channels asked for, rate, user metadata)
SESSION_METADATA = "asyncdonkey.session"
PROFILE = ""


class McapSink:
    """One MCAP file, written from one thread.

    Args:
        path: the file (created or truncated).
        encoder: turns ticks into messages.
        metadata: string key/values saved as the ``asyncdonkey.session`` metadata record.
        fsync: flush to the device at sync points.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        chunk_size: bytes after which a chunk is ended even between sync points.
        open_file: opens the file (tests pass one that fails like a full disk).
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
        from mcap.writer import CompressionType, Writer

        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in comp:
            raise ValueError(f"McapRecorder({path}): compression must be one of {sorted(comp)}, got {compression!r}")
        self.path = os.fspath(path)
        self.encoder = encoder
        self.fsync = fsync
        self._file: IO[bytes] = (open_file or _open)(self.path)
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp[compression])
        self._writer.start(profile=PROFILE, library="asyncdonkey")
        self._metadata = {str(k): str(v) for k, v in (metadata or {}).items()}
        self._schemas: dict[tuple[str, str, bytes], int] = {}
        self._channels: dict[str, int] = {}
        self.times: TimeMap | None = None
        """set by the recorder before it queues the first tick"""
        self._anchored = False
        self._broken: OSError | None = None
        self._closed = False
        # counters read by BackgroundWriter.stats
        self.unsynced = 0
        self.sync_requested = False
        self.durable = 0
        self.syncs = 0
        self.messages = 0
        self._written = 0

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
        """Write one tick's messages (a :class:`~.encode.TickSnapshot` as a tuple) into the open chunk."""
        snap = TickSnapshot(*payload)
        if self._broken is not None:
            raise OSError(f"{self.path}: not written after an earlier write error ({self._broken})")
        times = self.times
        if times is None:  # pragma: no cover - the recorder sets it before queueing
            raise RuntimeError(f"{self.path}: no time anchor")
        w = self._writer
        try:
            if not self._anchored:
                w.add_metadata(CLOCK_METADATA, times.as_metadata())
                if self._metadata:
                    w.add_metadata(SESSION_METADATA, self._metadata)
                self._anchored = True
            for spec, data, log_ns, pub_ns in self.encoder.encode(snap, times):
                w.add_message(self._channel(spec), log_ns, data, pub_ns)
                self.messages += 1
        except OSError as exc:
            self._broken = exc
            raise
        self._written += 1
        self.unsynced += 1

    def sync(self) -> bool:
        """End the open chunk, hand it to the OS and (with ``fsync``) to the device."""
        self.sync_requested = False
        if not self.unsynced or self._broken is not None:
            return False
        try:
            self._writer.flush()
            if self.fsync:
                os.fsync(self._file.fileno())
        except OSError as exc:
            self._broken = exc
            raise
        self.unsynced = 0
        self.durable = self._written
        self.syncs += 1
        return True

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._broken is None:
                self._writer.finish()  # ends the open chunk and writes the summary and footer
                self.durable = self._written
                self.unsynced = 0
                if self.fsync:
                    self._file.flush()
                    os.fsync(self._file.fileno())
        finally:
            try:
                self._file.close()
            except OSError as exc:
                logger.error("%s: closing failed: %r", self.path, exc)


def _open(path: str) -> IO[bytes]:
    return open(path, "wb")
