"""The queue and writer thread behind the recorders: ``run()`` only queues, a thread does the disk work.

:class:`BackgroundWriter` is what :class:`~asyncdonkey.parts.tub.TubWriter` and
:class:`~asyncdonkey.parts.mcap.McapRecorder` share: a bounded queue that the tick appends to (drop newest
when full, counted), a writer thread that polls it (the tick never wakes the thread: see ``_POLL_BUSY_S``),
sync points after ``sync_every`` records or ``sync_interval_s`` seconds, commands applied in order with the
records, a draining ``shutdown()`` with a timeout, and on the virtual clock a hold on time while records are
in hand (disk work takes no virtual time, like executor work). See ``docs/recording.md`` for the policies.

A disk that answers with errors (full, failing) is retried at a bounded rate: after a failed write or sync
point the thread leaves the disk alone for ``_RETRY_MIN_S``, doubling to ``_RETRY_MAX_S`` while the errors
go on, and retries the failed sync point before any further record. Records meanwhile wait in the queue
(and the newest are dropped once it is full, counted), so recording resumes by itself when space returns.

What a recorder brings is its *sink*, the object that owns the files, used only from the writer thread:

* ``write(t, payload)``: write one record (``t`` is what the recorder queued as the record's time);
  raising ``OSError`` counts the record as failed;
* ``sync() -> bool``: make what was written durable (False: nothing to do; raising ``OSError`` leaves the
  records unsynced, and the sync point is retried); ``unsynced`` (records written since the last sync
  point) and ``sync_requested`` (a sync point is wanted now);
* ``close()``: a last sync, then close the files;
* ``durable``, ``syncs``, ``bad_values``: counters read for :attr:`BackgroundWriter.stats`; optionally
  ``lost``: records ``write()`` took that never reached the file (an MCAP chunk the disk had no room for at
  close), moved from ``written`` to ``failed``.
"""

from __future__ import annotations

import asyncio
import atexit
import functools
import logging
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..clock import get_clock
from ..ratelimit import LogThrottle

__all__ = ["BackgroundWriter", "WriterStats"]

logger = logging.getLogger(__name__)

_LATENCY_WINDOW = 4096
#: How often the idle writer thread looks at the queue: every 5 ms while records arrive, every 50 ms after a
#: second without any. The tick never wakes the thread itself: waking a sleeping thread (``Event.set``, a pipe
#: write) is a system call that measured 25-70 µs here, and the woken thread then competes for the GIL while
#: the tick still runs. Polling costs at most 5 ms of extra write latency, which nothing waits for.
_POLL_BUSY_S = 0.005
_POLL_IDLE_S = 0.05
_BUSY_WINDOW_S = 1.0
#: The pause after a failed write or sync point: 50 ms after the first error, doubling to 1 s while errors go
#: on. Retrying at once would spin on a full disk (each attempt fails in microseconds); the cap bounds how long
#: recording waits once space is back.
_RETRY_MIN_S = 0.05
_RETRY_MAX_S = 1.0
#: How long ``shutdown()`` still waits, after giving up on the queue, for the thread to close the files (so
#: that the summary it logs counts what closing lost). The thread is then usually in a pause, which ends at once.
_CLOSE_WAIT_S = 0.5


@dataclass(frozen=True)
class WriterStats:
    """A snapshot of a recorder's counters (records of this session).

    ``accepted = written + failed + abandoned + queued`` (give or take the record being written).
    """

    accepted: int
    """records ``run()`` took."""
    written: int
    """records handed to the files (a tub's catalog line, an MCAP tick's messages). An MCAP tick is in the file
    from the sync point that ends its chunk; ticks of a chunk the disk never took are moved to ``failed`` when
    the file is closed, so after ``shutdown()`` this is exactly what the file holds."""
    durable: int
    """records covered by a completed sync point."""
    dropped: int
    """records ``run()`` refused because the queue was full (drop newest)."""
    failed: int
    """records lost to write errors (e.g. a full disk): not in the files."""
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
    """``run()`` to record written: p50 and p99 over the last 4096 records, max over all."""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class BackgroundWriter:
    """The queue, thread, sync points, shutdown and counters of a recorder part (see the module docstring).

    A subclass checks its arguments with :meth:`_check_writer_args`, opens its sink, then calls
    :meth:`_start_writer`. Its ``run()`` appends ``(t, time.monotonic(), payload)`` to ``self._queue`` when
    ``len(self._queue) < self._queue_size`` (else counts ``self._dropped``), and bumps ``self._accepted`` and
    ``self._high_water``: a few attribute operations, kept inline in each ``run()`` because they are the
    tick's whole cost.
    """

    @staticmethod
    def _check_writer_args(
        where: str, queue_size: int, sync_every: int, sync_interval_s: float, drain_timeout_s: float
    ) -> None:
        if not (isinstance(queue_size, int) and queue_size > 0):
            raise ValueError(f"{where}: queue_size must be a positive integer, got {queue_size!r}")
        if not (isinstance(sync_every, int) and sync_every > 0):
            raise ValueError(f"{where}: sync_every must be a positive integer, got {sync_every!r}")
        if not sync_interval_s > 0:
            raise ValueError(f"{where}: sync_interval_s must be positive, got {sync_interval_s!r}")
        if not drain_timeout_s > 0:
            raise ValueError(f"{where}: drain_timeout_s must be positive, got {drain_timeout_s!r}")

    def _start_writer(
        self,
        sink: Any,
        label: str,
        *,
        queue_size: int,
        sync_interval_s: float,
        sync_every: int,
        drain_timeout_s: float,
        copy_values: bool = False,
        time_fn: Callable[[], float] | None = None,
        base_index: int = 0,
    ) -> None:
        self._log = LogThrottle(5.0)
        self._sink = sink
        self._label = label
        self._base_index = base_index
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
        # disk errors (writer thread): the pause before the next attempt, see _RETRY_MIN_S
        self._retry_at = 0.0  # monotonic time of the next attempt; 0 while the disk answers
        self._backoff = 0.0
        self._failing_since: float | None = None
        self._sync_failed = False  # the last sync point failed: it is retried before any further record
        self._give_up = False  # a disk error during shutdown: what is still queued counts as failed
        # thread coordination
        self._wake = threading.Event()
        self._release_time: Callable[[], None] = lambda: None  # undoes the virtual clock's hold, if any
        self._notify_idle: Callable[[], object] = _noop  # wakes a virtual-clock loop when the queue runs dry
        self._closing = False
        self._abandon = False
        self._closed = False
        self._thread = threading.Thread(target=self._thread_main, name=label, daemon=True)
        self._thread.start()
        self._atexit = functools.partial(_shutdown_at_exit, weakref.ref(self))
        atexit.register(self._atexit)

    def _resolve_now(self) -> float:
        """Pick the timestamp source on the first record (the loop is only known once the car runs): wall-clock
        seconds, or on a virtual-clock loop the wall time at the first record advanced by virtual time. That
        wall time is taken to the whole millisecond: a record's millisecond timestamp then rounds its virtual
        time alone, the same way run after run (an anchor half a millisecond off would round ticks 50 ms apart
        to 49 and 51 by float error)."""
        try:
            clock = get_clock(asyncio.get_running_loop())
        except RuntimeError:
            clock = None
        if clock is not None and clock.is_virtual:
            vnow = clock.now
            wall0, v0 = time.time_ns() // 1_000_000 / 1000, vnow()
            self._now = self._on_virtual_time(lambda: wall0 + (vnow() - v0))
        else:
            self._now = time.time
        return self._now()

    def _on_virtual_time(self, now: Callable[[], float]) -> Callable[[], float]:
        """Make disk work take no virtual time (like executor work): returns ``now`` wrapped to wake the thread
        for each record instead of letting it poll, holds the loop's time while records are in hand, and has
        the thread tell the loop when the queue runs dry, so time moves on without waiting for a poll."""
        wake = self._wake
        loop = asyncio.get_running_loop()
        hold = getattr(loop, "hold_time_while", None)
        if hold is not None:
            self._release_time = hold(self._has_unwritten, self._label)
            self._notify_idle = lambda: loop.call_soon_threadsafe(_noop)

        def virtual_now() -> float:
            wake.set()
            return now()

        return virtual_now

    def _has_unwritten(self) -> bool:
        """Records or commands handed over and not yet written (read from the loop thread). False while the
        thread pauses after a disk error: virtual time does not wait for a broken disk (records then queue up
        and the newest are dropped, as on the real clock)."""
        if self._retry_at:
            return False
        return bool(self._queue) or self._accepted > self._written + self._failed

    # ---------------------------------------------------------------------------------- commands
    def flush(self, timeout: float | None = None) -> bool:
        """Block until every record accepted so far is written and durable. Not for the drive loop's thread.

        Returns False on timeout, when the sync point failed (a full disk) or when the writer has stopped.
        """
        if self._closed or not self._thread.is_alive():
            return False
        done = threading.Event()
        synced = [False]

        def sync_and_signal() -> None:
            try:
                self._sync()
                synced[0] = not self._sync_failed
            finally:
                done.set()

        self._command(sync_and_signal)
        return done.wait(timeout) and synced[0]

    def _command(self, fn: Callable[..., Any], *args: Any) -> None:
        if self._closed:
            raise RuntimeError(f"{self._label}: writer is shut down")
        self._queue.append((None, fn, args))  # commands bypass the bound: tiny, rare, never dropped

    # ---------------------------------------------------------------------------------- the thread
    def _thread_main(self) -> None:
        app = self._sink
        q = self._queue
        wake = self._wake
        mono = time.monotonic
        sync_every = self._sync_every
        latencies = self._latencies
        sync_due = 0.0
        last_record = -_BUSY_WINDOW_S
        try:
            while not self._abandon:
                if self._retry_at:  # the disk answered with an error
                    if self._give_up:
                        self._fail_queued()
                        break
                    if not self._closing and self._pause():
                        continue
                    if self._sync_failed:  # retry the sync point first: records wait until it succeeds
                        sync_due = self._sync(sync_due)
                        continue
                    # else the next record is the retry
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
                    pause = self._io_error()
                    self._warn(
                        "write", "%s: a record was not written (%s); next attempt in %.2f s; %d not written so far",
                        exc, pause, self._failed,
                    )  # fmt: skip
                    continue  # the pause first: no sync point attempt right after a failure
                except Exception as exc:  # a bug must not stop recording; say so loudly
                    self._failed += 1
                    logger.exception("%s: unexpected error writing a record: %r", self._label, exc)
                else:
                    self._written += 1
                    if self._retry_at:
                        self._recovered()
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
                logger.error("%s: closing the files failed: %s", self._label, exc)

    def _run_command(self, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
        try:
            fn(*args)
        except Exception as exc:
            logger.error("%s: %s failed: %r", self._label, getattr(fn, "__name__", fn), exc)

    def _sync(self, sync_due: float = 0.0) -> float:
        """Run a sync point; returns the next sync deadline. After an error the thread pauses (``_io_error``)
        and retries this sync point before any further record."""
        app = self._sink
        mono = time.monotonic
        t0 = mono()
        try:
            did = app.sync()
        except OSError as exc:
            self._sync_errors += 1
            self._sync_failed = True
            pause = self._io_error()
            self._warn(
                "sync",
                "%s: sync point failed (%s); %d records wait for it; next attempt in %.2f s; %d failures so far",
                exc, app.unsynced, pause, self._sync_errors,
            )  # fmt: skip
            return t0 + self._sync_interval
        self._sync_failed = False
        if not did:
            # nothing to do; a sink that still holds unsynced records is asked again a sync interval later,
            # not at once (a deadline left in the past would spin the thread)
            return t0 + self._sync_interval if app.unsynced else sync_due
        if self._retry_at:
            self._recovered()
        t1 = mono()
        if t1 - t0 > self._sync_max:
            self._sync_max = t1 - t0
        oldest = self._oldest_unsynced
        if oldest is not None:
            self._durable_lag_max = max(self._durable_lag_max, t1 - oldest)
            self._oldest_unsynced = None
        return sync_due

    # ---------------------------------------------------------------------------------- disk errors
    def _io_error(self) -> float:
        """Start or lengthen the pause after a failed write or sync point; returns its length in seconds.

        During shutdown there is no pause: the error is the last attempt, and what is still queued then counts
        as failed (waiting out ``drain_timeout_s`` against a disk that answers with errors helps nobody).
        """
        now = time.monotonic()
        if self._failing_since is None:
            self._failing_since = now
        self._backoff = min(_RETRY_MAX_S, max(_RETRY_MIN_S, self._backoff * 2))
        self._retry_at = now + self._backoff
        if self._closing:
            self._give_up = True
        return self._backoff

    def _pause(self) -> bool:
        """Sleep until the next attempt after a disk error; True while it has not come (a wake-up, from
        ``shutdown()`` or a record on the virtual clock, ends the sleep early and the loop asks again)."""
        wait = self._retry_at - time.monotonic()
        if wait <= 0:
            return False
        self._log_drops()
        if self._wake.wait(wait):
            self._wake.clear()
        return True

    def _recovered(self) -> None:
        """A write or sync point worked again: end the pauses and say how long the disk was failing."""
        since = self._failing_since
        self._retry_at = 0.0
        self._backoff = 0.0
        self._failing_since = None
        if since is not None:
            self._warn(
                "resumed", "%s: writing again after %.1f s of disk errors (%d records not written, %d dropped so far)",
                time.monotonic() - since, self._failed, self._dropped,
            )  # fmt: skip

    def _fail_queued(self) -> None:
        """Shutdown met a failing disk: count what is still queued as failed instead of waiting for space.
        Commands still run (a ``flush()`` caller gets its answer)."""
        if self._abandon:  # shutdown() gave up first and counted the queue as abandoned
            return
        q = self._queue
        n = 0
        while q:
            t_wall, fn, args = q.popleft()
            if t_wall is None:
                self._run_command(fn, args)
            else:
                n += 1
        self._failed += n
        if n:
            logger.error("%s: %d queued records not written: the disk failed during shutdown", self._label, n)

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
        suffix = self._log.ready(key, time.monotonic(), "similar")
        if suffix is not None:
            logger.warning(msg + suffix, self._label, *args)

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
            # Not waiting for that is safe: whatever moment the process then exits at, the files are consistent
            # (each sink's crash promises).
            self._abandon = True
            self._wake.set()
            left = sum(1 for e in list(self._queue) if e[0] is not None)
            self._abandoned = left
            if left:
                logger.error(
                    "%s: %d queued records not written: the disk did not keep up before shutdown", self._label, left
                )
            else:  # nothing was lost: the thread is still finishing the record in hand or closing the files
                logger.warning(
                    "%s: still closing the files after the shutdown timeout; nothing queued was lost", self._label
                )
            self._thread.join(_CLOSE_WAIT_S)
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
    def stats(self) -> WriterStats:
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
        app = self._sink
        lost = getattr(app, "lost", 0)
        return WriterStats(
            accepted=self._accepted,
            written=self._written - lost,
            durable=app.durable - self._base_index,
            dropped=self._dropped,
            failed=self._failed + lost,
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


def _shutdown_at_exit(ref: weakref.ref[BackgroundWriter]) -> None:
    writer = ref()
    if writer is not None:
        writer.shutdown()


def _noop() -> None:
    pass
