"""``TubWriter``: records Donkeycar Tub v2 without ever making the drive loop wait for the disk.

The tick only hands the record over: :meth:`TubWriter.run` checks the input count, reads the clock, and
appends ``(timestamp, values)`` to a queue (the values are the very objects the tick passed, not copies —
a few microseconds whatever the image size). A writer thread does the rest: converting values, JPEG/PNG
encoding (OpenCV, which releases the GIL), writing images and catalog lines, and sync points
(:mod:`.appender`).

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

import asyncio
import atexit
import functools
import logging
import os
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ...clock import get_clock
from ...ratelimit import LogThrottle
from .appender import TubAppender
from .fileio import TubFileIO

__all__ = ["TubWriter", "TubWriterStats"]

logger = logging.getLogger(__name__)

_LATENCY_WINDOW = 4096
#: How often the idle writer thread looks at the queue: every 5 ms while records arrive, every 50 ms after a
#: second without any. The tick never wakes the thread itself: waking a sleeping thread (``Event.set``, a pipe
#: write) is a system call that measured 25-70 µs here, and the woken thread then competes for the GIL while
#: the tick still runs. Polling costs at most 5 ms of extra write latency, which nothing waits for.
_POLL_BUSY_S = 0.005
_POLL_IDLE_S = 0.05
_BUSY_WINDOW_S = 1.0


@dataclass(frozen=True)
class TubWriterStats:
    """A snapshot of a :class:`TubWriter`'s counters (records of this session).

    ``accepted = written + failed + abandoned + queued`` (give or take the record being written).
    """

    accepted: int
    """records ``run()`` took."""
    written: int
    """records whose catalog line was written."""
    durable: int
    """records covered by a completed sync point."""
    dropped: int
    """records ``run()`` refused because the queue was full (drop newest)."""
    failed: int
    """records lost to write errors (e.g. a full disk)."""
    abandoned: int
    """records still queued when ``shutdown()`` gave up waiting."""
    bad_values: int
    """values left out of records (wrong type, NaN); the rest of each record was kept."""
    queued: int
    queue_high_water: int
    queue_size: int
    syncs: int
    sync_errors: int
    sync_max_ms: float
    durable_lag_max_ms: float
    """worst time from ``run()`` to the sync point that made the record durable."""
    write_latency_ms: dict[str, float] = field(default_factory=dict)
    """``run()`` to catalog line written: p50 and p99 over the last 4096 records, max over all."""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class TubWriter:
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

    ``run(*values)`` returns the number of records in the tub once everything accepted is written
    (Donkeycar returns its ``current_index``, the same count), typically wired to ``tub/num_records``.
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
        where = f"TubWriter({base_path})"
        if not (isinstance(queue_size, int) and queue_size > 0):
            raise ValueError(f"{where}: queue_size must be a positive integer, got {queue_size!r}")
        if not (isinstance(sync_every, int) and sync_every > 0):
            raise ValueError(f"{where}: sync_every must be a positive integer, got {sync_every!r}")
        if not sync_interval_s > 0:
            raise ValueError(f"{where}: sync_interval_s must be positive, got {sync_interval_s!r}")
        if not drain_timeout_s > 0:
            raise ValueError(f"{where}: drain_timeout_s must be positive, got {drain_timeout_s!r}")
        self._log = LogThrottle(5.0)
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
        self._label = f"TubWriter({self.base_path})"
        self._n = len(self.inputs)
        self._base_index = app.index
        self._queue: deque[tuple[Any, Any, Any]] = deque()
        self._queue_size = queue_size
        self._copy = bool(copy_values)
        self._now: Callable[[], float] = time_fn if time_fn is not None else self._resolve_now
        self._sync_interval = float(sync_interval_s)
        self._sync_every = sync_every
        self._drain_timeout = float(drain_timeout_s)
        # tick-side counters (written by the loop thread only)
        self._accepted = 0
        self._dropped = 0
        self._high_water = 0
        # writer-thread counters
        self._written = 0
        self._failed = 0
        self._abandoned = 0
        self._sync_errors = 0
        self._sync_max = 0.0
        self._durable_lag_max = 0.0
        self._latencies: deque[float] = deque(maxlen=_LATENCY_WINDOW)
        self._latency_max = 0.0
        self._oldest_unsynced: float | None = None  # run() time of the first record since the last sync
        self._dropped_logged = 0
        # thread coordination
        self._wake = threading.Event()
        self._release_time: Callable[[], None] = lambda: None  # undoes the virtual clock's hold, if any
        self._notify_idle: Callable[[], object] = _noop  # wakes a virtual-clock loop when the queue runs dry
        self._closing = False
        self._abandon = False
        self._closed = False
        self._thread = threading.Thread(target=self._thread_main, name=self._label, daemon=True)
        self._thread.start()
        self._atexit = functools.partial(_shutdown_at_exit, weakref.ref(self))
        atexit.register(self._atexit)

    # ------------------------------------------------------------------------------------ the tick
    def run(self, *values: Any) -> int:
        """Hand one record over to the writer thread; never blocks. Returns the tub's record count."""
        if len(values) != self._n:
            raise TypeError(f"{self._label}: expected {self._n} values for {self.inputs}, got {len(values)}")
        q = self._queue
        n = len(q)
        if n >= self._queue_size:
            if self._closed:
                raise RuntimeError(f"{self._label}: run() after shutdown()")
            self._dropped += 1
            return self._base_index + self._accepted
        if self._copy:
            values = _copied(values)
        q.append((self._now(), time.monotonic(), values))
        if n >= self._high_water:
            self._high_water = n + 1
        self._accepted += 1
        return self._base_index + self._accepted

    def _resolve_now(self) -> float:
        """Pick the timestamp source on the first record (the loop is only known once the car runs)."""
        try:
            clock = get_clock(asyncio.get_running_loop())
        except RuntimeError:
            clock = None
        if clock is not None and clock.is_virtual:
            vnow = clock.now
            wall0, v0 = time.time(), vnow()
            wake = self._wake

            def virtual_now() -> float:
                # On virtual time the disk's work must take no time (like executor work): wake the thread
                # for each record instead of letting it poll, and hold time while it has records in hand.
                wake.set()
                return wall0 + (vnow() - v0)

            self._now = virtual_now
            loop = asyncio.get_running_loop()
            hold = getattr(loop, "hold_time_while", None)
            if hold is not None:
                self._release_time = hold(self._has_unwritten, self._label)
                # and tell the loop when the queue runs dry, so time moves on without waiting for a poll
                self._notify_idle = lambda: loop.call_soon_threadsafe(_noop)
        else:
            self._now = time.time
        return self._now()

    def _has_unwritten(self) -> bool:
        """Records or commands handed over and not yet written (read from the loop thread)."""
        return bool(self._queue) or self._accepted > self._written + self._failed

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

    def flush(self, timeout: float | None = None) -> bool:
        """Block until every record accepted so far is written and durable. Not for the drive loop's thread.

        Returns False on timeout (or when the writer has stopped).
        """
        if self._closed or not self._thread.is_alive():
            return False
        done = threading.Event()

        def sync_and_signal() -> None:
            try:
                self._sync()
            finally:
                done.set()

        self._command(sync_and_signal)
        return done.wait(timeout)

    def _command(self, fn: Callable[..., Any], *args: Any) -> None:
        if self._closed:
            raise RuntimeError(f"{self._label}: writer is shut down")
        self._queue.append((None, fn, args))  # commands bypass the bound: tiny, rare, never dropped

    # ---------------------------------------------------------------------------------- the thread
    def _thread_main(self) -> None:
        app = self._appender
        q = self._queue
        wake = self._wake
        mono = time.monotonic
        sync_every = self._sync_every
        latencies = self._latencies
        sync_due = 0.0
        last_record = -_BUSY_WINDOW_S
        try:
            while not self._abandon:
                try:
                    t_wall, t_mono, payload = q.popleft()
                except IndexError:
                    if app.sync_requested or (app.unsynced and mono() >= sync_due):
                        sync_due = self._sync(sync_due)
                        continue
                    self._log_drops()
                    if self._closing:
                        break
                    now = mono()
                    poll = _POLL_BUSY_S if now - last_record < _BUSY_WINDOW_S else _POLL_IDLE_S
                    if app.unsynced:
                        poll = min(poll, max(0.0, sync_due - now))
                    # set by shutdown(), and per record on the virtual clock only: the tick never signals
                    if wake.wait(poll) and not self._closing:
                        wake.clear()
                    continue
                if self._abandon:  # shutdown() gave up and counted what is queued, this one included
                    q.appendleft((t_wall, t_mono, payload))
                    break
                if t_wall is None:  # a command: (None, function, args)
                    self._run_command(t_mono, payload)
                    continue
                try:
                    app.write(t_wall, payload)
                except OSError as exc:
                    self._failed += 1
                    self._warn("write", "%s: a record was not written (%s); %d lost so far", exc, self._failed)
                except Exception as exc:  # a bug must not stop recording; say so loudly
                    self._failed += 1
                    logger.exception("%s: unexpected error writing a record: %r", self._label, exc)
                else:
                    self._written += 1
                    if not q:
                        self._notify_idle()
                    last_record = mono()
                    lat = last_record - t_mono
                    latencies.append(lat)
                    if lat > self._latency_max:
                        self._latency_max = lat
                    if app.unsynced == 1:
                        sync_due = mono() + self._sync_interval
                        self._oldest_unsynced = t_mono
                if app.sync_requested or app.unsynced >= sync_every or (app.unsynced and mono() >= sync_due):
                    sync_due = self._sync(sync_due)
                if self._dropped != self._dropped_logged:
                    self._log_drops()
        except BaseException as exc:  # pragma: no cover - defensive: report why recording stopped
            logger.exception("%s: writer thread stopped: %r", self._label, exc)
        finally:
            try:
                app.close()
            except Exception as exc:
                logger.error("%s: final sync failed: %r", self._label, exc)

    def _run_command(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        try:
            fn(*args)
        except Exception as exc:
            logger.error("%s: %s failed: %r", self._label, getattr(fn, "__name__", fn), exc)

    def _sync(self, sync_due: float = 0.0) -> float:
        """Run a sync point; returns the next sync deadline (a retry after an error)."""
        app = self._appender
        mono = time.monotonic
        t0 = mono()
        try:
            did = app.sync()
        except OSError as exc:
            self._sync_errors += 1
            self._warn("sync", "%s: sync point failed (%s); will retry; %d failures so far", exc, self._sync_errors)
            return t0 + self._sync_interval
        if did:
            t1 = mono()
            if t1 - t0 > self._sync_max:
                self._sync_max = t1 - t0
            oldest = self._oldest_unsynced
            if oldest is not None:
                self._durable_lag_max = max(self._durable_lag_max, t1 - oldest)
                self._oldest_unsynced = None
        return sync_due

    def _bad_value(self, key: str, exc: Exception) -> None:
        self._warn(("value", key), "%s: channel %r: value left out of the record: %s", key, exc)

    def _log_drops(self) -> None:
        dropped = self._dropped
        if dropped != self._dropped_logged and self._log.allow("drops", time.monotonic()):
            logger.warning(
                "%s: the disk is behind: %d records dropped (queue full at %d; newest dropped)",
                self._label,
                dropped,
                self._queue_size,
            )
            self._dropped_logged = dropped

    def _warn(self, key: object, msg: str, *args: Any) -> None:
        if self._log.allow(key, time.monotonic()):
            held = self._log.take_suppressed(key)
            logger.warning(msg + (f" (+{held} similar)" if held else ""), self._label, *args)

    # ---------------------------------------------------------------------------------- shutdown
    def shutdown(self, timeout: float | None = None) -> None:
        """Stop accepting records, write what is queued (up to ``timeout``, default ``drain_timeout_s``),
        make it durable and close the files. Records still queued after the timeout are counted in
        ``stats.abandoned`` and logged. Safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        self._queue_size = 0  # run() now refuses (and raises) instead of queueing
        self._release_time()
        atexit.unregister(self._atexit)
        self._closing = True
        self._wake.set()
        self._thread.join(self._drain_timeout if timeout is None else timeout)
        if self._thread.is_alive():
            # Give up: the thread stops after the record in hand and closes the files when the disk lets it.
            # Not waiting for that is safe: whatever moment the process then exits at, the tub is consistent.
            self._abandon = True
            self._wake.set()
            left = sum(1 for e in list(self._queue) if e[0] is not None)
            self._abandoned = left
            logger.error(
                "%s: %d queued records not written: the disk did not keep up before shutdown", self._label, left
            )
        s = self.stats
        level = logging.WARNING if (s.dropped or s.failed or s.abandoned or s.bad_values) else logging.INFO
        logger.log(
            level,
            "%s: %d records written (%d durable), %d dropped, %d failed, %d abandoned, %d values left out",
            self._label,
            s.written,
            s.durable,
            s.dropped,
            s.failed,
            s.abandoned,
            s.bad_values,
        )

    close = shutdown

    # ---------------------------------------------------------------------------------- reporting
    @property
    def durable_index(self) -> int:
        """Records in the tub that a completed sync point made durable (all sessions)."""
        return self._appender.durable

    @property
    def stats(self) -> TubWriterStats:
        lat = np.asarray(list(self._latencies), dtype=float) * 1e3
        latency = (
            {
                "p50": float(np.percentile(lat, 50)),
                "p99": float(np.percentile(lat, 99)),
                "max": self._latency_max * 1e3,
            }
            if lat.size
            else {}
        )
        app = self._appender
        return TubWriterStats(
            accepted=self._accepted,
            written=self._written,
            durable=app.durable - self._base_index,
            dropped=self._dropped,
            failed=self._failed,
            abandoned=self._abandoned,
            bad_values=app.bad_values,
            queued=sum(1 for e in list(self._queue) if e[0] is not None),
            queue_high_water=self._high_water,
            queue_size=self._queue_size if not self._closed else 0,
            syncs=app.syncs,
            sync_errors=self._sync_errors,
            sync_max_ms=self._sync_max * 1e3,
            durable_lag_max_ms=self._durable_lag_max * 1e3,
            write_latency_ms=latency,
        )

    def __repr__(self) -> str:
        return f"<TubWriter {self.base_path} inputs={self.inputs}>"


def _copied(values: tuple[Any, ...]) -> tuple[Any, ...]:
    return tuple(v.copy() if isinstance(v, np.ndarray | list) else v for v in values)


def _index_set(indexes: int | Iterable[int]) -> set[int]:
    if isinstance(indexes, int):
        return {indexes}
    return {int(i) for i in indexes}


def _shutdown_at_exit(ref: weakref.ref[TubWriter]) -> None:
    writer = ref()
    if writer is not None:
        writer.shutdown()


def _noop() -> None:
    pass
