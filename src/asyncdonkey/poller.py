"""Hardware pollers: a blocking read called at its own rate off the event loop thread.

An IMU read over I2C or a camera grab blocks for milliseconds; doing it inside the tick (as Donkeycar's
non-threaded parts do) delays every part after it. A :class:`Poller` calls the read off the loop on its own
:class:`~asyncdonkey.clock.Schedule` (the drive loop's deadline rule) and publishes each result into a
:class:`~asyncdonkey.latest.Latest` cell. The tick reads the newest value without waiting and can see how old
it is.

Add a poller to a vehicle like any part: its ``async update()`` runs as a background task and ``run()``
returns the newest value (``None`` until the first read succeeds)::

    imu = Poller(mpu.read, rate_hz=60, name="imu")
    vehicle.add(imu, outputs=["imu/sample"])

How it runs, and why:

* **On a real loop** the poller is its own thread, sleeping to absolute deadlines of the runtime clock
  (``time.monotonic()``) and calling ``read()`` directly. Waking on the event loop and handing every read to an
  executor costs two thread hand-offs and several loop passes per sample, more than the wait itself; the
  thread costs one wake-up per sample. It sleeps with ``time.sleep`` (measured cheaper per wake-up than a
  timed lock or a timerfd read) for the time left to the deadline, at most :data:`STOP_CHECK_S` at a time, so
  after :meth:`Poller.shutdown` a slow poller's thread still ends within that time and never reads again.
  A sample's CPU is mostly that wake-up, after which every line of Python runs on cold caches, so the thread
  does as little as it can per sample: one clock read (the sample's timestamp, which also says how long to
  sleep), no method or property calls of its own (it publishes and follows the schedule inline), and on Linux
  no clock read after the sleep (``time.sleep`` there is an absolute wait that cannot return early).
* **On the virtual clock** it waits on exact loop timers and reads through a one-thread executor, whose work
  the virtual loop waits for without moving time: a read takes no virtual time and samples land exactly on
  their deadlines, run after run.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import sysconfig
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from .clock import TIME_EPS, Clock, DeadlineWaiter, Schedule, TickGrid, get_clock, grid_start, tick_grid
from .clock._timerslack import exact_sleeps
from .latest import Latest, Sample, _new_sample
from .ratelimit import LogThrottle

__all__ = ["STOP_CHECK_S", "Poller"]

#: Longest single sleep of a poller thread: how late a slow poller's thread may notice shutdown().
STOP_CHECK_S = 0.1

#: ``time.sleep`` sleeps until an absolute ``CLOCK_MONOTONIC`` time (``clock_nanosleep(TIMER_ABSTIME)``, Python
#: 3.11+ where the C library has it: Linux, the BSDs), computed from the clock when it is called and rounded up,
#: and resumes that same sleep after a signal. Then ``sleep(deadline - t)`` with ``t`` taken from
#: ``time.monotonic()`` earlier never returns before ``deadline``, and the thread need not read the clock again
#: to check. Elsewhere it does check.
_SLEEP_UNTIL_MONOTONIC = bool(sysconfig.get_config_var("HAVE_CLOCK_NANOSLEEP"))

#: In a drive, a poller reads on the drive's tick grid, this long before the ticks its deadlines share (see
#: :func:`~asyncdonkey.clock.grid_start`): long enough for a quick read to be published before the tick starts
#: (the thread's wake-up is as late as the tick's, give or take some tens of microseconds), short enough that
#: the machine is still awake from the read when the tick's timer fires. Measured on a 2-core VM with a 60 Hz
#: poller beside a 20 Hz drive, leads of 0.1 to 0.3 ms cost the same CPU within the noise, and less than 0.5 ms
#: or half a poll period; at 0.1 ms, in a phase of late wake-ups, most ticks of one run lost the race. Beside a
#: drive in precise mode the lead is longer by the drive's longest spin (:attr:`TickGrid.spin_s
#: <asyncdonkey.clock.TickGrid.spin_s>`): a read due inside the spin would wait for the tick to end.
POLL_LEAD_S = 2e-4

logger = logging.getLogger(__name__)
T = TypeVar("T")


class Poller(Generic[T]):
    """Calls ``read()`` ``rate_hz`` times a second in a worker thread and keeps the newest result.

    * Deadline-based like the drive loop (no drift); a read longer than a period makes the next one start at
      once, and when more than a period behind the missed deadlines are skipped (``.skipped``), never burst.
    * A read that raises is counted in ``.errors`` and logged at most once per second; polling goes on.
    * Each poller owns one worker thread (named ``poll:<name>``), so a slow device cannot starve other
      executor users.
    * In a drive it reads on the drive's ticks, :data:`POLL_LEAD_S` ahead of those its deadlines share: the
      machine wakes once for both, and a quick read is in the tick (see :func:`~asyncdonkey.clock.grid_start`).
    """

    def __init__(self, read: Callable[[], T], rate_hz: float, name: str | None = None) -> None:
        if not callable(read):
            raise TypeError(f"Poller: read must be callable, got {read!r}")
        if not rate_hz > 0:
            raise ValueError(f"Poller({name or read!r}): rate_hz must be positive, got {rate_hz!r}")
        self.read = read
        self.rate_hz = float(rate_hz)
        self.name = name or getattr(read, "__qualname__", "poller")
        self.latest: Latest[T] = Latest()
        self.errors = 0
        self.skipped = 0
        self.last_error: BaseException | None = None
        self._origin: float | None = None
        self._running = False
        self._log = LogThrottle(1.0)

    @property
    def sample(self) -> Sample[T] | None:
        return self.latest.sample

    @property
    def reads(self) -> int:
        """Reads that succeeded so far: the sequence number of the newest sample (nothing to count per read)."""
        s = self.latest.sample
        return 0 if s is None else s.seq

    def run(self) -> T | None:
        s = self.latest.sample
        if s is None:
            return None
        self._origin = s[1]  # s.timestamp, s.value: indexing a tuple is the interpreter's fast path, each tick
        return s[0]

    def output_origin(self) -> float | None:
        """When the value ``run()`` returned was read: re-publishing it on later ticks does not make it young."""
        return self._origin

    async def update(self) -> None:
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        self._running = True
        try:
            if clock.is_virtual:
                await self._poll_on_loop(loop, clock)
            else:
                await self._poll_in_thread(loop, clock)
        finally:
            self._running = False

    def shutdown(self) -> None:
        self._running = False

    # ------------------------------------------------------------------------------ real loop: a thread
    async def _poll_in_thread(self, loop: asyncio.AbstractEventLoop, clock: Clock) -> None:
        done: asyncio.Future[None] = loop.create_future()
        grid = tick_grid()  # (read in this task: a thread does not see the task's context)
        thread = threading.Thread(
            target=self._thread_main, args=(clock, loop, done, grid), name=f"poll:{self.name}", daemon=True
        )
        thread.start()
        try:
            await done
        finally:
            self.shutdown()  # cancelled: the thread ends after its current read

    def _thread_main(
        self, clock: Clock, loop: asyncio.AbstractEventLoop, done: asyncio.Future[None], grid: TickGrid | None
    ) -> None:
        now = clock.now
        try:
            exact_sleeps()  # wake on the deadline, as the drive's timerfd does, not up to 50 µs after it
            recheck = not (_SLEEP_UNTIL_MONOTONIC and now is time.monotonic)
            self._poll_blocking(now, time.sleep, recheck, grid)
        finally:
            with contextlib.suppress(RuntimeError):  # the loop is already closed: nobody is waiting
                loop.call_soon_threadsafe(_set_done, done)

    def _poll_blocking(
        self, now: Callable[[], float], sleep: Callable[[float], object], recheck: bool, grid: TickGrid | None = None
    ) -> None:
        """The poller thread's loop, until :meth:`shutdown`: ``sleep(seconds)`` blocks, ``now()`` reads the clock.

        ``grid``: the drive's ticks; the first read is then on it, :data:`POLL_LEAD_S` ahead of the next point
        that falls on it (see :func:`~asyncdonkey.clock.grid_start`), else at once.

        ``recheck``: read the clock after every sleep and sleep again if it woke before the deadline (needed
        unless ``sleep`` is known never to return early, see :data:`_SLEEP_UNTIL_MONOTONIC`).

        Per sample, on time: one check of ``_running``, ``read()``, one clock read, then what
        :meth:`Latest.publish` and the on-time case of :meth:`Schedule.advance
        <asyncdonkey.clock.Schedule.advance>` do, inline (the module docstring says why). An overrun of more
        than a period goes to the :class:`Schedule`, which decides what to skip.
        """
        cell = self.latest
        prev = cell.sample
        seq = 0 if prev is None else prev.seq  # a restarted poller goes on numbering its samples
        read = self.read
        new_sample, sample_type, stop_check = _new_sample, Sample, STOP_CHECK_S  # locals: no globals touched
        t = now()
        lead = POLL_LEAD_S if grid is None else POLL_LEAD_S + grid.spin_s  # (ahead of a precise drive's spin)
        sched = Schedule(self.rate_hz, grid_start(grid, self.rate_hz, t, lead))
        # The read count as a float: ``t0 + k / rate`` is then the Schedule's deadline to the bit (a count below
        # 2**53 converts to float exactly, as the Schedule's int does in its division), and counting makes no int
        # object per read; the thread wakes to cold caches, where each allocation is a few cache misses.
        t0, rate, k = sched.t0, sched.rate_hz, float(sched.k)
        behind = sched.period + TIME_EPS  # Schedule.advance's test for "more than a period behind"
        deadline = sched.deadline
        while True:
            left = deadline - t
            if left > 0.0:  # sleeps at least the time left: never early (a float constant: the fast compare)
                if left > stop_check:  # a slow poller still sees shutdown() within STOP_CHECK_S
                    sleep(stop_check)
                    if not self._running:
                        return
                    t = now()
                    continue
                sleep(left)
                if not self._running:
                    return
                if recheck:
                    t = now()
                    if t < deadline:
                        continue
            elif not self._running:
                return
            try:
                value = read()
            except Exception as exc:
                t = now()
                self._read_failed(exc, t)
            else:
                t = now()
                seq += 1
                cell.sample = new_sample(sample_type, (value, t, seq))  # Latest.publish, inline
                subscribers = cell._subscribers
                if subscribers:
                    for callback in subscribers:
                        callback(value, t)
            k += 1.0
            deadline = t0 + k / rate  # Schedule's deadline of tick k
            if t - deadline > behind:
                sched.k = int(k) - 1  # the tick that just ended
                sched.advance(t)
                self.skipped = sched.skipped
                k, deadline = float(sched.k), sched.deadline

    # ---------------------------------------------------------------- virtual clock: timers + executor
    async def _poll_on_loop(self, loop: asyncio.AbstractEventLoop, clock: Clock) -> None:
        now = clock.now
        executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"poll:{self.name}")
        waiter = DeadlineWaiter(loop)
        sched = Schedule(self.rate_hz, grid_start(tick_grid(), self.rate_hz, now()))  # (no lead: time stands still)
        try:
            while self._running:
                deadline = sched.deadline
                if now() < deadline:
                    await waiter.wait_until(deadline)
                if not self._running:
                    break
                try:
                    value = await loop.run_in_executor(executor, self.read)
                except Exception as exc:
                    self._read_failed(exc, now())
                else:
                    self.latest.publish(value, now())
                if sched.advance(now()):
                    self.skipped = sched.skipped
        finally:
            waiter.close()
            executor.shutdown(wait=False, cancel_futures=True)

    def _read_failed(self, exc: Exception, t: float) -> None:
        self.errors += 1
        self.last_error = exc
        if self._log.allow("read", t):
            held = self._log.take_suppressed("read")
            logger.warning(
                "poller %r: read failed (%d errors so far%s): %r",
                self.name,
                self.errors,
                f", {held} not logged" if held else "",
                exc,
            )


def _set_done(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)
