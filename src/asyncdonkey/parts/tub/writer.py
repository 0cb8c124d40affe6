"""``TubWriter``: records Donkeycar Tub v2 without ever making the drive loop wait for the disk.

The tick only hands the record over: :meth:`TubWriter.run` checks the input count, reads the clock, and
appends ``(timestamp, values)`` to a queue (the values are the very objects the tick passed, not copies —
a few microseconds whatever the image size). A writer thread does the rest: converting values, JPEG/PNG
encoding (OpenCV, which releases the GIL), writing images and catalog lines, and sync points
(:mod:`.appender`). The queue and the thread are :class:`~asyncdonkey.parts.background_writer.BackgroundWriter`,
shared with the MCAP recorder.

Queue policy: **bounded, drop newest.** When ``queue_size`` records are waiting (the disk has fallen behind),
``run()`` refuses the new record, counts it in ``stats.dropped`` and returns at once; the writer thread logs
the drops (rate-limited). Why newest and not oldest: a record that was accepted is a promise, and the tick
cannot discard the oldest without reaching into the writer thread's end of the queue; dropping at the door
keeps ``run()`` lock-free, and the tub keeps one contiguous run of records before the stall instead of
records with holes cut at random. Indexes are given by the writer thread as records are written, so a
dropped record never leaves a gap (Donkeycar's reader identifies records by their position).

Durability: a sync point runs after ``sync_every`` records or ``sync_interval_s`` seconds after the first
record not yet synced, whichever comes first, and right after deletions and when a new catalog gets its
first line. So while the disk keeps up, every record is durable at most ``sync_interval_s`` (1 s) plus one
sync's duration after it was written; ``stats.durable_lag_max_ms`` reports the worst seen. Manifests are
rewritten only at sync points (Donkeycar rewrites them on every record), atomically.

Values must not be mutated after they are handed over (Donkeycar's camera parts return a new array each
frame; so does the runtime's contract). A part that reuses a buffer in place should be recorded with
``copy_values=True``, which copies numpy arrays and lists in ``run()``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from ..background_writer import BackgroundWriter, WriterStats
from .appender import TubAppender
from .fileio import TubFileIO

__all__ = ["TubWriter", "TubWriterStats"]

#: The counters of a :class:`TubWriter` (the recorders share one stats type).
TubWriterStats = WriterStats


class TubWriter(BackgroundWriter):
    """A drive-loop part that records its inputs to a Donkeycar Tub v2 directory, off the loop thread.

    Use it as Donkeycar's ``TubWriter``::

        writer = TubWriter("data/tub_1", inputs=["cam/image_array", "user/angle", "user/throttle",
                           "user/mode"], types=["image_array", "float", "float", "str"])
        v.add(writer, inputs=writer.inputs, outputs=["tub/num_records"], run_condition="recording")

    Args:
        base_path: the tub directory; created if missing, else appended to (a new session) after repairing
            what a crash may have left (:func:`~.appender.repair_tub`).
        inputs, types: the channels to record and their Tub v2 types (``float``, ``int``, ``str``,
            ``boolean``, ``nparray``, ``list``, ``vector``, ``image_array``, ``gray16_array``).
        metadata: user metadata, ``["key:value", ...]`` like Donkeycar, or a mapping.
        max_catalog_len: records per catalog file (Donkeycar's default 1000).
        queue_size: records that may wait for the disk before ``run()`` starts dropping new ones.
        sync_interval_s, sync_every: a sync point at most this long after a record is written, or after this
            many records, whichever first.
        fsync: flush to the device at sync points (default). False keeps the atomic manifest rewrites but
            protects only against the process dying, not against a power cut.
        jpeg_quality: JPEG quality for ``image_array`` (75, as Donkeycar's PIL default).
        copy_values: copy numpy arrays and lists in ``run()`` (for producers that reuse buffers).
        drain_timeout_s: how long ``shutdown()`` waits for the queue to drain.
        time_fn: wall-clock seconds for ``_timestamp_ms``. Default: ``time.time``, or, when the part runs on a
            virtual-clock loop, wall time at the first record advanced by the loop's virtual time, so
            recordings made in simulation carry their simulated timing.
        file_io: file operations (tests inject a slow or full disk, see :class:`~.fileio.TubFileIO`).

    ``run(*values)`` returns the number of records in the tub: those whose catalog line has been written,
    typically wired to ``tub/num_records``. A record still queued is counted once the writer thread has
    written it (usually within 5 ms: Donkeycar, which writes inside ``run()``, returns one more), and one that
    fails to write (a full disk) is never counted.
    """

    def __init__(
        self,
        base_path: str | os.PathLike[str],
        inputs: Sequence[str] = (),
        types: Sequence[str] = (),
        metadata: Iterable[str] | Mapping[str, Any] = (),
        max_catalog_len: int = 1000,
        *,
        queue_size: int = 200,
        sync_interval_s: float = 1.0,
        sync_every: int = 100,
        fsync: bool = True,
        jpeg_quality: int = 75,
        copy_values: bool = False,
        drain_timeout_s: float = 5.0,
        time_fn: Callable[[], float] | None = None,
        file_io: TubFileIO | None = None,
    ) -> None:
        self._check_writer_args(f"TubWriter({base_path})", queue_size, sync_every, sync_interval_s, drain_timeout_s)
        self._appender = app = TubAppender(
            base_path,
            inputs,
            types,
            metadata,
            max_catalog_len,
            file_io=file_io,
            fsync=fsync,
            jpeg_quality=jpeg_quality,
            on_bad_value=self._bad_value,
        )
        self.base_path: str = str(app.base)
        self.inputs: list[str] = list(app.inputs)
        self.types: list[str] = list(app.types)
        self.session_id: str = app.session[1]
        self._n = len(self.inputs)
        self._start_writer(
            app,
            f"TubWriter({self.base_path})",
            queue_size=queue_size,
            sync_interval_s=sync_interval_s,
            sync_every=sync_every,
            drain_timeout_s=drain_timeout_s,
            copy_values=copy_values,
            time_fn=time_fn,
            base_index=app.index,
        )

    # ------------------------------------------------------------------------------------ the tick
    def run(self, *values: Any) -> int:
        """Hand one record over to the writer thread; never blocks. Returns the records written to the tub so
        far (all sessions; not this one, which is only queued), never counting one that failed."""
        if len(values) != self._n:
            raise TypeError(f"{self._label}: expected {self._n} values for {self.inputs}, got {len(values)}")
        q = self._queue
        n = len(q)
        if n >= self._queue_size:
            if self._closed:
                raise RuntimeError(f"{self._label}: run() after shutdown()")
            self._dropped += 1
            return self._appender.index
        written = self._appender.index  # read before queueing: the count never includes this record
        if self._copy:
            values = _copied(values)
        q.append((self._now(), time.monotonic(), values))
        if n >= self._high_water:
            self._high_water = n + 1
        self._accepted += 1
        return written

    # ---------------------------------------------------------------------------------- commands
    @property
    def tub(self) -> TubWriter:
        """Donkeycar compatibility: ``TubWiper(writer.tub)`` works as with Donkeycar's ``TubWriter``."""
        return self

    def delete_last_n_records(self, n: int) -> None:
        """Mark the last ``n`` records handed to ``run()`` (and not deleted yet) as deleted. Never blocks.

        Applied by the writer thread in order with the records, so "last" means the ones accepted before this
        call, even if they are still queued; persisted at once (a sync point follows).
        """
        self._command(self._appender.delete_last, int(n))

    def delete_records(self, indexes: int | Iterable[int]) -> None:
        """Mark records as deleted (``deleted_indexes`` in the manifest). Never blocks."""
        self._command(self._appender.delete, _index_set(indexes))

    def restore_records(self, indexes: int | Iterable[int]) -> None:
        """Undo :meth:`delete_records`. Never blocks."""
        self._command(self._appender.restore, _index_set(indexes))

    def _bad_value(self, key: str, exc: Exception) -> None:
        self._warn(("value", key), "%s: channel %r: value left out of the record: %s", key, exc)

    # ---------------------------------------------------------------------------------- reporting
    @property
    def durable_index(self) -> int:
        """Records in the tub that a completed sync point made durable (all sessions)."""
        return self._appender.durable

    def __repr__(self) -> str:
        return f"<TubWriter {self.base_path} inputs={self.inputs}>"


def _copied(values: tuple[Any, ...]) -> tuple[Any, ...]:
    return tuple(v.copy() if isinstance(v, np.ndarray | list) else v for v in values)


def _index_set(indexes: int | Iterable[int]) -> set[int]:
    if isinstance(indexes, int):
        return {indexes}
    return {int(i) for i in indexes}
