"""The one clock the runtime reads, the one deadline schedule every periodic task follows, and how to wait.

Every duration, deadline and timestamp in asyncdonkey comes from a :class:`Clock` taken from the event loop
the code runs on. On a :class:`~asyncdonkey.virtual_loop.VirtualClockLoop` the clock *is* the loop's virtual time,
so a test controls everything the runtime measures. On a real loop the clock reads ``time.monotonic()``
(``CLOCK_MONOTONIC``, nanosecond resolution on Linux) rather than ``loop.time()``, because uvloop's
``loop.time()`` only has millisecond resolution.

Three pieces, used by the drive loop, the hardware pollers and every periodic part:

* :class:`Schedule` says *when*: tick ``k`` is due at ``t0 + k / rate_hz``; a tick that ends more than a period
  behind skips (and counts) the deadlines it missed instead of running them back to back.
* :class:`DeadlineWaiter` says *how to wait* for an absolute deadline on the runtime clock, without spinning:

  - **Linux**: a ``timerfd`` armed at the deadline on ``CLOCK_MONOTONIC`` (absolute, no slack) and watched by
    the running loop (``add_reader``; asyncio and uvloop alike). One timerfd per waiter, re-armed for every
    wait, closed by :meth:`DeadlineWaiter.close`. Lateness is the kernel's wake-up latency plus one loop pass:
    a few tenths of a millisecond on a small virtual machine, and never early.
  - **Elsewhere** (or when a timerfd cannot be created): the loop's own timers. asyncio's selector loop wakes
    up to a millisecond late (``epoll``/``kqueue`` timeouts are rounded up to whole milliseconds); uvloop's timers
    count whole milliseconds of a cached clock, so the wait is armed one millisecond long and re-checked, for a
    lateness of one to two milliseconds. Never early either way: the waiter re-arms until the clock has passed
    the deadline.
  - **Virtual clock**: an exact loop timer at the deadline, so runs are deterministic and free of float drift.

* **Precise mode** (``DeadlineWaiter(precise=True)``, ``Vehicle.run(precise=True)``) trades CPU for tighter
  ticks: it sleeps to a little *before* the deadline and spins the rest on the clock. Where the machine's
  wake-ups have a long tail it sleeps twice, to a guard before that and then to it (a short sleep wakes more
  punctually than a long one, see :data:`_GUARD_S` and :data:`_TWO_STAGE_ABOVE_S`). The spin window is learned
  from the wake-up lateness actually observed: the 99th percentile of the recent lateness of the timer before
  the spin, less :data:`PRECISE_TOLERANCE_S` (the lateness precise mode accepts, 20 µs), so that 99 % of the
  ticks start within that tolerance while the spin lasts no longer than it takes. A quiet machine spins for
  tens of microseconds, a noisy one for longer, and nobody spins for a guessed constant. The spin never takes
  more than half a millisecond, nor more than :data:`SPIN_BUDGET` (3 %) of the time between deadlines:
  preemption on a loaded machine cannot be spun away, only paid for. A timer wakes later after a long sleep
  than after a short one, so what is learned is kept per octave of the period: a new waiter takes over the
  samples last learned from at its own rate.

Wall-clock time (``time.time()``) is used only where a human or a file needs it, e.g. ``_timestamp_ms`` in
recorded records.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import heapq
import logging
import math
import time
import weakref
from array import array
from collections.abc import Callable
from math import ceil
from os import read as _read
from typing import Any, Literal, NamedTuple

from . import _timerfd

__all__ = [
    "PRECISE_TOLERANCE_S",
    "SPIN_BUDGET",
    "TICK_EPS",
    "TIME_EPS",
    "Clock",
    "DeadlineWaiter",
    "Schedule",
    "TickGrid",
    "get_clock",
    "grid_start",
    "tick_grid",
]

logger = logging.getLogger(__name__)

#: Float noise in time arithmetic (0.4 + 0.2 = 0.6000000000000001) is neither an overrun nor "behind".
TIME_EPS = 1e-9
#: In periods: a deadline this close to ``now`` counts as passed when working out how far behind a tick is.
TICK_EPS = 1e-6


class TickGrid(NamedTuple):
    """A drive's deadlines: ``origin + k * period`` on the runtime clock (``origin`` is its first tick's).

    ``spin_s``: how long before each deadline the drive's thread may spin (precise mode; 0 otherwise), holding
    the interpreter: a read in another thread that is due inside it is published only after the tick.
    """

    origin: float
    period: float
    spin_s: float = 0.0


#: The grid of the drive whose background work this is: set by the drive around the creation of its parts'
#: ``update()`` tasks, which copy it with the rest of their context (so two drives on one loop each have
#: their own, and code outside a drive sees None).
_TICK_GRID: contextvars.ContextVar[TickGrid | None] = contextvars.ContextVar("asyncdonkey_tick_grid", default=None)


def tick_grid() -> TickGrid | None:
    """The tick grid of the drive this code runs under (in a part's ``update()`` task), or None."""
    return _TICK_GRID.get()


def grid_start(grid: TickGrid | None, rate_hz: float, now: float, lead_s: float = 0.0) -> float:
    """The first deadline of a schedule of ``rate_hz`` started at ``now``: on ``grid`` (a drive's ticks, see
    :func:`tick_grid`), ``lead_s`` before it, at the first such point not before ``now``; without a grid,
    ``now`` itself.

    Phase-locked to the ticks, a background schedule whose period divides the drive's (or is a multiple of it)
    has deadlines that fall on tick deadlines, and the machine wakes once for both instead of twice: on a
    2-core VM a 60 Hz poller beside a 20 Hz drive cost 10-15 % less CPU a fraction of a millisecond ahead of
    the ticks than half a poll period off them. The lead also has a quick read published before the tick that
    shares its deadline, instead of racing it: the tick gets a sample a fraction of a millisecond old.
    """
    if grid is None:
        return now
    period = 1.0 / rate_hz
    origin = grid.origin - lead_s
    return origin + math.ceil((now - origin) / period - TICK_EPS) * period


class Schedule:
    """Deadlines ``t0 + k / rate_hz`` with skip-and-count, the rule every periodic task here follows.

    Computing each deadline from ``t0`` (never by adding periods) means no drift. :meth:`advance` is called
    once a tick's work has ended: when the next deadline has already passed by less than a period, the next
    tick starts at once (it is late, not skipped); when the tick ended more than a period after the next
    deadline, the deadlines it overran are skipped and counted in :attr:`skipped`, and the schedule resumes at
    the latest deadline already passed. A backlog is never run back to back (no burst).
    """

    __slots__ = ("deadline", "k", "period", "rate_hz", "skipped", "t0")

    def __init__(self, rate_hz: float, t0: float) -> None:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"Schedule: rate_hz must be a positive finite number, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.t0 = t0
        #: Number of the current tick (:meth:`advance` moves it, and :attr:`deadline` with it).
        self.k = 0
        #: When the current tick (number :attr:`k`) is due: ``t0 + k / rate_hz``. A plain attribute that
        #: :meth:`advance` keeps up to date (a hot loop reads it once per tick; a property would cost a call).
        self.deadline = t0 + self.k / self.rate_hz
        self.skipped = 0

    def advance(self, end: float) -> int:
        """The current tick's work ended at ``end``: move to the next deadline. Returns the deadlines skipped."""
        rate = self.rate_hz
        t0 = self.t0
        k = self.k + 1
        deadline = t0 + k / rate
        if end - deadline > self.period + TIME_EPS:
            behind = math.floor((end - t0) * rate + TICK_EPS)
            missed = behind - k
            self.skipped += missed
            self.k = behind
            self.deadline = t0 + behind / rate
            return missed
        self.k = k
        self.deadline = deadline
        return 0


WaitMode = Literal["timerfd", "loop-timer", "virtual"]

# Precise mode: how the spin window is learned from observed timer lateness.
_LATE_SAMPLES = 1024  # recent lateness samples kept: on a VM the slow wake-ups come in bursts, minutes apart
_LATE_QUANTILE = 0.99  # the ticks precise mode keeps within its tolerance
_LATE_REFRESH = 32  # recompute the window every this many samples
_LATE_WARMUP = 64  # waits with the start window before the first estimate (a few early samples mislead)
#: The lateness precise mode accepts at that quantile: the window is the quantile less this. Spinning the
#: last few microseconds too would cost CPU on every tick for nothing a car can notice: every microsecond
#: taken off the window is a microsecond less spin per tick (at 100 Hz, 20 µs is 0.2 % of a core, about 40 %
#: of what Donkeycar's whole loop costs there), while a servo pulse is refreshed only every 16-20 ms.
PRECISE_TOLERANCE_S = 20e-6
_WINDOW_FLOOR_S = 5e-6  # the window is at least this (the spin's own check-to-start cost) ...
#: ... and at most this: measured on a busy 2-core VM, spinning longer than about half a millisecond made the
#: next wake-ups *later* (the scheduler's fairness counts the spin against the task), so the window grew, and
#: the spin with it, until precise mode was less precise than the default.
_WINDOW_CEIL_S = 0.5e-3
#: ... and at most this fraction of the time between successive deadlines: a loaded machine's preemption
#: outliers cannot be spun away, and chasing them would make precise mode spin for a large part of each period.
SPIN_BUDGET = 0.03
#: Until the first samples are in, when no precise waiter has learned a window yet: a guess at the lateness of
#: the second, short sleep (see :data:`_GUARD_S`), which on a 2-core VM was 46 µs at the median and at most
#: 125 µs at the 99th percentile, noisy hours included.
_WINDOW_START_S = 0.2e-3
#: The window the last precise waiter in this process learned: the machine's wake-up latency, which a new
#: waiter starts from instead of the guess (a drive restarted, a second periodic task).
_learned_window_s: float | None = None


class _Learned(NamedTuple):
    """What precise mode learned at one period class (:func:`_period_class`), samples oldest first."""

    late: array[float]  # the window's samples: the lateness of the sleep before the spin
    two_stage: bool  # whether that is the second of two sleeps (see _TWO_STAGE_ABOVE_S) or the only one
    firsts: array[float]  # the first sleep's lateness, for the choice between one sleep and two


#: What was last learned at each *period class* (:func:`_period_class`): how late a timer wakes depends on how
#: long the machine slept before it. Measured on a 2-core VM, a timerfd woke about 85 µs late at the median and
#: 180 µs at the 99th percentile after 50 ms of sleep (20 Hz), against 55 and 65 µs after 10 ms (100 Hz). A
#: waiter starting at a period this process has learned takes over that period's samples and adds its own to
#: them: a 20 Hz drive restarted after a 100 Hz one does not spin for 100 Hz's latency, and a drive restarted
#: at the same rate keeps its quantile over a thousand wake-ups instead of starting again from the largest of
#: its first few dozen (one outlier would set the window).
_learned: dict[int, _Learned] = {}


def _oldest_first(ring: array[float], n: int, size: int) -> array[float]:
    """A copy of a ring of at most ``size`` samples that ``n`` samples have been written to (appended until it
    is full, then each over the oldest, at ``n % size``), oldest first."""
    start = n % size if len(ring) == size else 0
    return ring[start:] + ring[:start]


def _period_class(gap_s: float) -> int:
    """The octave of the time between two deadlines, in microseconds (20 Hz and 100 Hz differ, 20 and 25 Hz
    do not): the key of :data:`_learned`."""
    return int(gap_s * 1e6).bit_length()


#: Precise mode sleeps twice: its first timer is armed this long before the spin window, and a second, short
#: sleep takes it to the window. How late a timer wakes depends on how long the machine slept: measured on a
#: 2-core VM, after 10-50 ms a timerfd woke 55-125 µs late at the median and 90-425 µs at the 99th percentile,
#: while a second sleep of up to a millisecond woke 46 µs late at the median and 60-120 µs at the 99th
#: percentile (an idle processor that just ran sleeps shallowly: the idle governor, or the hypervisor's halt
#: polling, expects it back soon). The window is then learned from the second sleep, whose tail is close to its
#: median, and the spin shrinks accordingly: in a loop of bare timerfd waits at 100 Hz, 125-150 µs of CPU per
#: tick against 186-189 µs for one sleep and the spin (103 µs without precise mode). The guard itself is not
#: spun: a longer one only makes the second sleep longer, so it is a constant, well over the first sleep's
#: 99th percentile.
_GUARD_S = 1e-3
_GUARD_SHARE = 0.1  # ... at most this fraction of the time between deadlines
#: ... and at least this, or precise mode sleeps once (1 kHz and faster): its sleeps are short already, and a
#: second wake-up per tick would cost more than the spin it saves.
_GUARD_MIN_S = 0.25e-3
#: A second sleep shorter than this is not armed (the rest is spun): it would wake later than the spin ends.
_SHORT_SLEEP_MIN_S = 50e-6
#: Two sleeps pay only where the first sleep's lateness has a long tail: one sleep spins about its 99th
#: percentile less its median (less the tolerance), two sleeps cost a wake-up more (25-40 µs measured) and spin
#: the second sleep's spread. So precise mode goes to two sleeps when that percentile is more than this over the
#: median, and back to one when it is less than :data:`_ONE_STAGE_BELOW_S` (in between either costs about the
#: same, and staying put keeps the window learned). An idle virtual machine's tail was 90-370 µs over its median;
#: a machine busy on its other core, or a small board, wakes within a few tens of microseconds, and there the
#: second wake-up cost more than it saved (106-112 against 113-130 µs of CPU per tick at 100 Hz beside a busy
#: core).
_TWO_STAGE_ABOVE_S = 75e-6
_ONE_STAGE_BELOW_S = 45e-6
_FIRST_SAMPLES = 256  # recent lateness samples of the first sleep, for that choice

#: How far a periodic timer's grid (``call_at(period=...)``) may fall behind the deadlines it stands for before it
#: is armed again on a new grid: it drifts by at most a nanosecond a period (see :meth:`DeadlineWaiter.call_at`).
_GRID_SLACK_NS = 2_000

#: Set to False to keep waits off timerfd (tests force the fallback this way; it is also the escape hatch for a
#: kernel or sandbox where timerfd misbehaves).
USE_TIMERFD = True


class _Wakeup:
    """A reusable awaitable for one waiting task: what an ``asyncio.Future`` does for a wait, minus the Future.

    A wait on a real loop would otherwise allocate a Future, and completing it schedules the task's wake-up as
    one more callback for the next loop pass. This object speaks the Future protocol the task needs
    (``_asyncio_future_blocking``, ``get_loop``, ``add_done_callback``, ``result``, ``cancel``; see
    :func:`asyncio.isfuture`) and is re-armed for every wait. :meth:`fire`, called from the timer's own loop
    callback, resumes the task in that same loop pass; a wake-up requested while a task is running (or a
    cancellation) goes through ``call_soon`` like a Future's would.
    """

    __slots__ = ("_asyncio_future_blocking", "_callback", "_cancel_msg", "_cancelled", "_context", "_loop")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._asyncio_future_blocking = False
        self._callback: Callable[[Any], object] | None = None
        self._context: Any = None
        self._cancelled = False
        self._cancel_msg: Any = None

    # the part of the Future protocol a Task uses
    def get_loop(self) -> asyncio.AbstractEventLoop:
        return self._loop

    def add_done_callback(self, fn: Callable[[Any], object], *, context: Any = None) -> None:
        self._callback, self._context = fn, context

    def remove_done_callback(self, fn: Callable[[Any], object]) -> int:
        if self._callback is fn:
            self._callback = self._context = None
            return 1
        return 0

    def done(self) -> bool:
        return self._callback is None

    def cancelled(self) -> bool:
        return self._cancelled

    def result(self) -> None:
        if self._cancelled:
            raise asyncio.CancelledError(*(() if self._cancel_msg is None else (self._cancel_msg,)))

    def cancel(self, msg: Any = None) -> bool:
        if self._callback is None:
            return False
        self._cancelled, self._cancel_msg = True, msg
        self.fire()
        return True

    def __await__(self) -> Any:
        self._cancelled, self._cancel_msg = False, None
        self._asyncio_future_blocking = True
        yield self
        self.result()

    # ours
    @property
    def waiting(self) -> bool:
        return self._callback is not None

    def fire(self) -> None:
        """Resume the waiting task (no-op if none): at once from a plain loop callback, else on the next pass."""
        cb, ctx = self._callback, self._context
        if cb is None:
            return
        self._callback = self._context = None
        loop = self._loop
        if self._cancelled or asyncio.current_task(loop) is not None:
            loop.call_soon(cb, self, context=ctx)
        elif ctx is not None:
            ctx.run(cb, self)
        else:
            cb(self)


class DeadlineWaiter:
    """Waits for absolute deadlines on the runtime clock, for one task at a time, reusing one OS timer.

    Create one per periodic task (the drive loop, a part's update loop), call :meth:`wait_until` for every
    deadline and :meth:`close` when done (or use it as a context manager). See the module docstring for the
    three ways it waits and their precision; :attr:`mode` says which one this waiter uses.

    Args:
        loop: the event loop it waits on (default: the running loop).
        precise: arm the timer early by a learned spin window and spin the rest on the clock (see
            :attr:`spin_window_s`). Costs CPU for the window on every wait, at most :data:`SPIN_BUDGET` of the
            time between successive deadlines; a no-op on the virtual clock.

    What a wait costs on Linux: one ``timerfd_settime`` to arm, one ``epoll`` wake-up of the loop, and the
    timer's loop callback resuming the waiting task directly (no Future, no extra loop pass, no ``read()``
    unless the task was busy elsewhere when the timer fired). Nothing is allocated per wait beyond a few numbers
    (the deadline in nanoseconds). A periodic :meth:`call_at` (``period=``) does not even arm: its timer is
    periodic and each wake-up reads the expiry count instead. Precise mode arms once or twice per deadline (a
    guard sleep, then the short sleep to the spin window) and never periodically.
    """

    __slots__ = (
        "__weakref__",
        "_call",
        "_call_deadline",
        "_call_early",
        "_call_target",
        "_closed",
        "_fast_arm",
        "_first_at",
        "_first_late",
        "_first_n",
        "_grid_ns",
        "_guard_s",
        "_handle",
        "_interval_ns",
        "_last_deadline",
        "_late",
        "_late_n",
        "_loop",
        "_now",
        "_on_loop_timer_cb",
        "_on_wake_cb",
        "_other_late",
        "_period_class",
        "_period_given",
        "_refresh_due",
        "_series_reader",
        "_tfd",
        "_timer_slop",
        "_two_stage",
        "_vfut",
        "_wakeup",
        "_watched",
        "mode",
        "precise",
        "spin_window_s",
        "waits",
    )

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None, *, precise: bool = False) -> None:
        loop = loop if loop is not None else asyncio.get_running_loop()
        clock = get_clock(loop)
        self._loop = loop
        self._now = clock.now
        self._wakeup = _Wakeup(loop)
        self._vfut: asyncio.Future[None] | None = None
        self._watched: asyncio.Future[Any] | None = None
        self._handle: asyncio.TimerHandle | asyncio.Handle | None = None
        self._tfd: _timerfd.Timerfd | None = None
        #: the timerfd's arm(deadline_ns) when a call_at re-arms for the deadline itself (timerfd, not precise)
        self._fast_arm: Callable[[int], None] | None = None
        self._closed = False
        # call_at(): the pending callback, its deadline and when its timer is armed (earlier in precise mode)
        self._call: Callable[[], float | None] | None = None
        self._call_deadline = self._call_target = math.inf
        self._call_early = False  # call_at(early=True): precise mode leaves the spin to the callback
        # call_at(period=...): the periodic timer's interval (0: armed once per deadline) and its next expiry
        self._interval_ns = 0
        self._grid_ns = -1
        # ... and the loop callback watching the timerfd for that series (None: _on_timerfd watches it)
        self._series_reader: Callable[[], None] | None = None
        #: precise mode on a timerfd: how long before the spin window the first of its two sleeps ends
        self._guard_s = 0.0
        self._two_stage = True  # precise mode sleeps twice (until the first sleep's lateness says otherwise)
        self._first_at = 0.0  # when the pending first sleep was armed to end (0: none pending)
        self._first_late = array("d")  # the first sleep's recent lateness, in both modes
        self._first_n = 0
        self._other_late = array("d")  # the window's samples of the other mode, kept for a switch back
        self._on_wake_cb = self._on_wake  # bound once: no bound-method object per wait
        self._on_loop_timer_cb = self._on_loop_timer
        self.precise = bool(precise) and not clock.is_virtual
        #: Precise mode: seconds before the deadline the timer is armed; the rest is spun. Learned.
        start = _WINDOW_START_S if _learned_window_s is None else _learned_window_s
        self.spin_window_s = start if self.precise else 0.0
        self._late = array("d")
        self._late_n = 0
        self._refresh_due = False
        self._last_deadline = math.inf
        self._period_class = 0  # of the time between this waiter's deadlines: not known yet
        self._period_given = False  # by call_at(period=): then a skip's longer gap does not change the class
        #: Waits that actually slept (the deadline had not passed yet).
        self.waits = 0
        # uvloop's timers count whole milliseconds of a clock cached at the start of each loop pass: arm them
        # a millisecond long so they do not fire early (asyncio's own loop times with time.monotonic()).
        self._timer_slop = 0.0 if isinstance(loop, asyncio.BaseEventLoop) else 1e-3
        self.mode: WaitMode = "virtual" if clock.is_virtual else "loop-timer"
        if not clock.is_virtual and USE_TIMERFD and _timerfd.AVAILABLE:
            self._open_timerfd(loop)

    def _open_timerfd(self, loop: asyncio.AbstractEventLoop) -> None:
        try:
            tfd = _timerfd.Timerfd()
        except OSError as exc:
            logger.debug("timerfd unavailable (%s): waiting on the loop's timers", exc)
            return
        try:
            loop.add_reader(tfd.fd, self._on_timerfd, tfd)
        except (NotImplementedError, RuntimeError, OSError, ValueError) as exc:
            tfd.close()
            logger.debug("the loop cannot watch a timerfd (%s): waiting on the loop's timers", exc)
            return
        self._tfd = tfd
        self.mode = "timerfd"
        self._fast_arm = None if self.precise else tfd.arm
        # an unclosed waiter must not leak its fd once collected (the loop's registration dies with the loop)
        weakref.finalize(self, tfd.close)

    # ------------------------------------------------------------------------------------------ callbacks
    def _on_timerfd(self, tfd: _timerfd.Timerfd | None) -> None:
        """The timerfd is readable (or, with ``tfd`` None, the loop timer fired): run a pending :meth:`call_at`
        callback, re-arming for the deadline it returns, or resume the waiting task. (A periodic series has a
        reader of its own while it lasts: :meth:`_watch_series`.)"""
        callback = self._call
        if callback is not None:
            t = self._now()
            target = self._call_target
            if self._first_at:
                self._first_woke(t)
            # Not yet: precise mode's first sleep (a guard before the window), a readiness left from an earlier
            # arming, or a loop timer rounded early. Sleep again, unless precise mode has too little time left
            # for that: it spins the rest then.
            if t < target and (not self.precise or target - t >= _SHORT_SLEEP_MIN_S):
                self._arm(target, t)
                return
            self._call = None
            if self.precise and not self._call_early:  # (an early callback reports its arrival: arrived())
                self._learn(t - target)
                deadline = self._call_deadline
                now = self._now
                while t < deadline:  # the last stretch is spun on the clock
                    t = now()
            # No read() of the timerfd: arming it again clears the expiry; if the callback ends the calls,
            # the next readiness finds nothing pending and consumes the expiry then.
            deadline = callback()
            if deadline is not None and self._call is None:
                arm = self._fast_arm
                if arm is not None:  # _pend's timerfd case without precise mode, written out: once per period
                    self._call = callback
                    self._call_deadline = self._call_target = deadline
                    self.waits += 1
                    arm(ceil(deadline * 1e9))
                    return
                self._pend(callback, deadline)  # the loop's timers, or precise mode's sleeps
            return
        wakeup = self._wakeup
        if wakeup.waiting:
            # No read() here: the waiter re-arms (which clears the expiry) before the loop polls again, or
            # comes back here not waiting and reads it then. One syscall less per wait; a stale readiness
            # cannot end a wait early, the waiter re-checks the clock.
            wakeup.fire()
        elif tfd is not None:
            tfd.fired()

    def _end_periodic(self) -> None:
        self._interval_ns = 0
        tfd = self._tfd
        if tfd is not None and tfd.fd >= 0:
            tfd.arm(0)  # disarms, and clears a pending expiry
        self._unwatch_series()

    def _watch_series(self, callback: Callable[[], float | None]) -> None:
        """Watch the timerfd with a loop callback of its own for ``callback``'s periodic series.

        A wake-up on the period is most of what a drive's idle tick costs, and it runs on caches gone cold over
        the period, where every attribute read, branch and call of Python is a few cache misses. So a periodic
        series gets the shortest path there is: ``read()`` the expiry count, call back, and check that the
        deadline it returns is the timer's next expiry. Nothing else can be pending then (no precise mode, no
        loop timer, no early readiness: the grid is never before a deadline, and an arming clears a stale
        expiry, which then reads as nothing fired). Anything off that path goes to :meth:`_pend`, and the end
        of the series (or :meth:`cancel_call`) gives the timerfd back to :meth:`_on_timerfd`.
        """
        tfd = self._tfd
        fd = tfd.fd  # type: ignore[union-attr]
        interval = self._interval_ns
        slack = _GRID_SLACK_NS

        def on_expiry() -> None:
            try:
                _read(fd, 8)
            except BlockingIOError:  # a readiness left from an earlier arming: nothing fired
                return
            if self._call is not callback:  # (defensive: the series ends before its reader is replaced)
                self._end_periodic()
                self._on_timerfd(tfd)
                return
            self._call = None  # (the callback may call call_at or cancel_call itself)
            try:
                deadline = callback()
            except BaseException:  # the series ends with its callback's error (raised to the loop)
                if self._call is None:
                    self._end_periodic()
                raise
            if deadline is None or self._call is not None:
                if self._call is None:  # the series ended: stop the periodic timer
                    self._end_periodic()
                return
            grid = self._grid_ns + interval
            if 0 <= grid - ceil(deadline * 1e9) <= slack:  # on the grid: already armed for it
                self._call = callback
                self._call_deadline = self._call_target = deadline
                self.waits += 1
                self._grid_ns = grid
                return
            self._pend(callback, deadline)  # off the grid (a skip): a new grid

        self._series_reader = on_expiry
        self._loop.add_reader(fd, on_expiry)

    def _unwatch_series(self) -> None:
        if self._series_reader is None:
            return
        self._series_reader = None
        tfd = self._tfd
        if tfd is not None and tfd.fd >= 0 and not self._loop.is_closed():
            self._loop.add_reader(tfd.fd, self._on_timerfd, tfd)

    def _on_loop_timer(self) -> None:
        self._handle = None
        self._on_timerfd(None)

    def _on_wake(self, _wake: object) -> None:
        fut = self._vfut
        if fut is not None:
            _set_done(fut)
        else:
            self._wakeup.fire()

    # ------------------------------------------------------------------------------------------- waiting
    async def wait_until(self, deadline: float, wake: asyncio.Future[Any] | None = None) -> bool:
        """Return at (never before) ``deadline`` on the runtime clock, or as soon as ``wake`` is done.

        Returns True when the deadline was reached, False when ``wake`` cut the wait short (``wake`` is only
        watched, never completed by the waiter). A deadline already passed returns at once on a real loop and
        after one loop pass on the virtual clock. One wait at a time per waiter.
        """
        if self._wakeup.waiting or self._vfut is not None:
            raise RuntimeError("DeadlineWaiter.wait_until: this waiter is already waiting (one task per waiter)")
        if self.mode == "virtual":
            return await self._wait_virtual(deadline, wake)
        if wake is not None and wake.done():
            return False
        now = self._now
        t = now()
        if t >= deadline:
            return True
        self.waits += 1
        target = self._target(deadline)
        if t < target:
            wakeup = self._wakeup
            if wake is not None and wake is not self._watched:
                # Watched once, not added and removed around every wait: a drive passes the same wake future
                # for thousands of ticks. A future watched earlier that completes later only causes a
                # spurious wake-up, and the loop below goes back to sleep.
                wake.add_done_callback(self._on_wake_cb)
                self._watched = wake
            try:
                self._arm_first(target, t)
                while True:
                    await wakeup
                    if wake is not None and wake.done():
                        self._disarm()
                        return False
                    t = now()
                    if self._first_at:
                        self._first_woke(t)
                    if t >= target or (self.precise and target - t < _SHORT_SLEEP_MIN_S):
                        break  # (precise mode spins what is left)
                    self._arm(target, t)  # precise mode's second sleep, or a wake-up before the deadline
            except BaseException:
                self._disarm()
                raise
            if self.precise:
                self._learn(t - target)
        while t < deadline:  # precise mode only: the last stretch is spun on the clock
            t = now()
        return True

    def _arm_first(self, target: float, now: float) -> None:
        """Arm for ``target``; in precise mode on a timerfd the first sleep ends a guard before it (see
        :data:`_GUARD_S`), unless that leaves no room for a second sleep. Only precise mode learns from its first
        sleeps, so only there is one pending (:attr:`_first_at` stays 0 otherwise)."""
        if not self.precise:
            self._arm(target, now)
            return
        first = target - self._guard_s
        if first <= now + _SHORT_SLEEP_MIN_S:
            first = target
        self._first_at = first
        self._arm(first, now)

    def _first_woke(self, t: float) -> None:
        """A wake-up at ``t`` while a first sleep is pending: with two sleeps, keep its lateness (with one, the
        window's sample is the first sleep's: :meth:`_learn`), unless it is a readiness left from an earlier
        arming (before the first sleep's end)."""
        first = self._first_at
        if t < first:
            return
        self._first_at = 0.0
        if self._two_stage:
            self._keep_first(t - first)

    def _keep_first(self, late: float) -> None:
        samples = self._first_late
        if len(samples) < _FIRST_SAMPLES:
            samples.append(late)
        else:
            samples[self._first_n % _FIRST_SAMPLES] = late
        self._first_n += 1

    def _arm(self, target: float, now: float) -> None:
        tfd = self._tfd
        if tfd is not None:
            tfd.arm(math.ceil(target * 1e9))
            return
        delay = target - now
        if self._timer_slop:
            delay = math.ceil(delay * 1e3) * 1e-3 + self._timer_slop
        self._handle = self._loop.call_later(delay, self._on_loop_timer_cb)

    def _disarm(self) -> None:
        tfd = self._tfd
        if tfd is not None:
            if tfd.fd >= 0:
                tfd.arm(0)
                tfd.fired()
            return
        handle = self._handle
        if handle is not None:
            handle.cancel()
            self._handle = None

    # --------------------------------------------------------------------------------- calling back
    def call_at(
        self,
        deadline: float,
        callback: Callable[[], float | None],
        *,
        early: bool = False,
        period: float | None = None,
    ) -> None:
        """Call ``callback()`` from the loop at (never before) ``deadline`` on the runtime clock; when it returns
        a number, call it again at that deadline, and so on until it returns ``None``.

        The callback form of :meth:`wait_until`, for a periodic job that is plain synchronous code (the drive
        loop's tick when no part awaits): the timer's own loop callback runs it and re-arms the timer for the
        deadline it returns, so a period costs no task resume, no coroutine frames, no awaitable and no call
        here. Same precision and modes as :meth:`wait_until` (precise mode spins the last stretch inside the
        timer callback). A deadline already passed calls back on the next loop pass, never from inside this
        call. One pending call per waiter, and not while a :meth:`wait_until` is waiting; :meth:`cancel_call`
        drops it.

        ``early=True``: in precise mode, call back as soon as the early timer wakes, up to the spin window
        before the deadline (or up to :data:`_SHORT_SLEEP_MIN_S` more, when the guard sleep woke too late for
        a second one), and leave the last stretch to the callback (``while now() < deadline``), which reports
        its first clock read with :meth:`arrived`. A callback that spins itself starts its work on the
        instruction after the spin; when the waiter spins instead, the call into the callback comes after the
        deadline, and on a small board that call, on caches gone cold over the period, takes tens of
        microseconds. Without precise mode it changes nothing.

        ``period``: the deadlines the callback returns are mostly ``period`` seconds apart (a drive's ticks).
        On a timerfd outside precise mode the timer is then armed periodic, on a grid of whole nanoseconds
        never before the deadlines: a deadline on the grid re-arms nothing, the kernel moves the timer on by
        itself; any other deadline (a skip after an overrun, a grid drifted more than
        :data:`_GRID_SLACK_NS` past the deadlines) re-arms it on a new grid. Precise mode sleeps once or twice
        per deadline on one-shot timers instead, and learns its window for this period from the first wait on.
        """
        if self._wakeup.waiting or self._vfut is not None:
            raise RuntimeError("DeadlineWaiter.call_at: this waiter is already waiting (one task per waiter)")
        self.cancel_call()
        self._unwatch_series()  # (a new series from inside the last one's callback: cancel_call found none)
        self._call_early = bool(early)
        if period is not None and not (period > 0 and math.isfinite(period)):
            raise ValueError(f"DeadlineWaiter.call_at: period must be a positive number of seconds, got {period!r}")
        # one nanosecond over the period: the grid then never falls before the deadlines it stands for (their
        # own nanoseconds round up), and drifts past them by at most a nanosecond a period, until re-armed
        self._interval_ns = (
            ceil(period * 1e9) + 1 if period is not None and self._tfd is not None and not self.precise else 0
        )
        self._period_given = period is not None  # (after cancel_call above)
        if period is not None and self.precise:  # the first wait already starts from this period's window
            self._enter_period_class(_period_class(period))
            self._last_deadline = deadline - period  # (and its spin budget and guard)
        self._pend(callback, deadline)

    def _pend(self, callback: Callable[[], float | None], deadline: float) -> None:
        """Make ``callback`` the pending call at ``deadline`` and arm for it (from :meth:`call_at`, and again
        after each call that returned its next deadline)."""
        self._call = callback
        self._call_deadline = deadline
        if self.mode == "virtual":
            # An exact loop timer whose callback is queued for the next pass, as a task woken by a timer would
            # be: among tasks and callbacks due at the same virtual instant, the order is what it was for a task
            # awaiting wait_until (their timers' order), run after run.
            loop = self._loop
            self._handle = loop.call_at(deadline, loop.call_soon, self._virtual_fire)
            return
        target = self._call_target = self._target(deadline)
        self.waits += 1
        interval = self._interval_ns
        if interval:
            ns = self._grid_ns = ceil(target * 1e9)
            self._tfd.arm_every(ns, interval)  # type: ignore[union-attr]
            if self._series_reader is None:
                self._watch_series(callback)
            return
        self._arm_first(target, self._now())

    def arrived(self, t: float) -> None:
        """From a precise-mode ``call_at(early=True)`` callback: the time it first read the clock. The spin window
        is learned from it rather than from the timer's own wake-up, so it also covers the way from the timer
        into the callback, which on caches gone cold over a long period is tens of microseconds. A no-op
        otherwise (a task's wait_until learns by itself)."""
        if self.precise and self._call_early:
            self._learn(t - self._call_target)

    def cancel_call(self) -> None:
        """Drop the pending :meth:`call_at` callback, if any (idempotent)."""
        self._period_given = False  # later waits find their period class from their gaps again
        if self._call is None:
            return
        self._call = None
        self._interval_ns = 0
        if self.mode == "virtual":
            if self._handle is not None:
                self._handle.cancel()
                self._handle = None
        else:
            self._disarm()
            self._unwatch_series()

    def _virtual_fire(self) -> None:
        callback = self._call
        if callback is None:  # cancelled after its timer fired
            return
        self._call = None
        self._handle = None
        deadline = callback()
        if deadline is not None and self._call is None:
            self._pend(callback, deadline)

    def _target(self, deadline: float) -> float:
        """When to arm the timer for ``deadline``: the deadline itself, or in precise mode the learned spin window
        before it (at most :data:`SPIN_BUDGET` of the time since the previous deadline)."""
        if not self.precise:
            return deadline
        if self._refresh_due:
            self._refresh_window()
        gap, self._last_deadline = deadline - self._last_deadline, deadline
        if gap > 0 and not self._period_given:
            self._enter_period_class(_period_class(gap))
        window = self.spin_window_s
        if gap > 0 and window > gap * SPIN_BUDGET:
            window = gap * SPIN_BUDGET
        if self._tfd is not None and self._two_stage:  # (the loop's timers are too coarse for a second sleep)
            guard = gap * _GUARD_SHARE if 0 < gap * _GUARD_SHARE < _GUARD_S else _GUARD_S
            self._guard_s = guard if guard >= _GUARD_MIN_S else 0.0
        else:
            self._guard_s = 0.0
        return deadline - window

    async def _wait_virtual(self, deadline: float, wake: asyncio.Future[Any] | None) -> bool:
        # A plain Future completed by a plain loop timer, as a bare asyncio.sleep would be: tasks woken at the
        # same virtual instant resume in the order their timers were scheduled, run after run.
        loop = self._loop
        if deadline <= loop.time():
            await asyncio.sleep(0)
            return True
        if wake is not None and wake.done():
            return False
        self.waits += 1
        fut = self._vfut = loop.create_future()
        handle = loop.call_at(deadline, _set_done, fut)  # exact: no float error accumulates
        if wake is not None:
            wake.add_done_callback(self._on_wake_cb)
        try:
            await fut
        finally:
            self._vfut = None
            handle.cancel()
            if wake is not None:
                wake.remove_done_callback(self._on_wake_cb)
        return not (wake is not None and wake.done() and loop.time() < deadline)

    def _learn(self, late: float) -> None:
        """Keep the recent lateness of the early timer. Called between the wake-up and the deadline, so it only
        stores: the window is worked out again when the next wait is armed (:meth:`_target`), after the work."""
        samples = self._late
        n = self._late_n
        if len(samples) < _LATE_SAMPLES:
            samples.append(late)
        else:
            samples[n % _LATE_SAMPLES] = late
        n = self._late_n = n + 1
        if n % _LATE_REFRESH == 0 and n >= _LATE_WARMUP:
            self._refresh_due = True
        if not self._two_stage:  # one sleep: it is the first sleep too
            self._keep_first(late)

    def _enter_period_class(self, cls: int) -> None:
        """The time between deadlines is in period class ``cls``: until this waiter has learned a window of its
        own, take over the samples last learned from at that class, if any, and set the window from them with
        its own. A waiter that has learned keeps its own samples whatever its deadlines do (irregular waits
        change class from one wait to the next)."""
        if cls == self._period_class:
            return
        self._period_class = cls
        if self._late_n < _LATE_WARMUP:
            past = _learned.get(cls)
            if past is not None:
                if self._first_n < _LATE_WARMUP:  # the first sleeps' too, for the choice
                    self._first_late = (past.firsts + self._firsts_oldest_first())[-_FIRST_SAMPLES:]
                    self._first_n = len(self._first_late)
                own = self._late if past.two_stage == self._two_stage else array("d")  # (of the same kind only)
                self._two_stage = past.two_stage
                self._late = samples = (past.late + own)[-_LATE_SAMPLES:]  # oldest first: the next replaces [0]
                self._late_n = len(samples)
                self._refresh_window()

    def _refresh_window(self) -> None:
        """Choose one sleep or two (:data:`_TWO_STAGE_ABOVE_S`), and set the spin window to the high quantile of
        the recent lateness of the sleep before the spin, less the tolerance."""
        self._refresh_due = False
        if self._first_n >= _LATE_WARMUP and self._tfd is not None:
            firsts = sorted(self._first_late)
            spread = firsts[int(_LATE_QUANTILE * (len(firsts) - 1))] - firsts[len(firsts) // 2]
            if spread > _TWO_STAGE_ABOVE_S if not self._two_stage else spread < _ONE_STAGE_BELOW_S:
                self._switch_stages()
        samples = self._late
        if not samples:  # two sleeps again, none learned of the second yet: the window so far until then
            return
        rank = len(samples) - min(len(samples) - 1, int(_LATE_QUANTILE * len(samples)))  # from the top, 1-based
        q = heapq.nlargest(rank, samples)[-1]
        global _learned_window_s
        self.spin_window_s = _learned_window_s = min(max(q - PRECISE_TOLERANCE_S, _WINDOW_FLOOR_S), _WINDOW_CEIL_S)
        if self._period_class:
            late = _oldest_first(samples, self._late_n, _LATE_SAMPLES)
            _learned[self._period_class] = _Learned(late, self._two_stage, self._firsts_oldest_first())

    def _firsts_oldest_first(self) -> array[float]:
        return _oldest_first(self._first_late, self._first_n, _FIRST_SAMPLES)

    def _switch_stages(self) -> None:
        """From two sleeps to one or back. The window's samples change kind with it, to those of the last time
        this waiter was in the other mode; going to one sleep for the first time, to the first sleep's lateness
        so far (which lacks the way from the timer into the callback that :meth:`arrived` measures, but the
        window learns it within :data:`_FIRST_SAMPLES` waits); going to two for the first time, to none (the
        window stays as it is until the second sleep's own samples are in)."""
        two = not self._two_stage
        current = self._late
        if two or len(self._other_late) >= _LATE_WARMUP:
            self._late = self._other_late
        else:
            self._late = self._firsts_oldest_first()
        self._other_late = current
        self._late_n = len(self._late)
        self._two_stage = two

    def max_spin_s(self, period: float) -> float:
        """The longest this waiter spins before a deadline when deadlines are ``period`` apart: precise mode's
        window at its ceiling or its budget, whichever is less (0 outside precise mode)."""
        return min(_WINDOW_CEIL_S, SPIN_BUDGET * period) if self.precise else 0.0

    @property
    def sleeps(self) -> int:
        """How many times precise mode slept before its spin at the last wait: 2 where the machine's wake-ups
        have a long tail (a guard sleep, then a short one; see :data:`_TWO_STAGE_ABOVE_S`), else 1 (and 1
        outside precise mode)."""
        return 2 if self.precise and self._two_stage and self._guard_s > 0 else 1

    # ------------------------------------------------------------------------------------------ lifetime
    @property
    def closed(self) -> bool:
        """:meth:`close` was called (a later wait still works, on the loop's timers)."""
        return self._closed

    def close(self) -> None:
        """Release the OS timer (idempotent). A waiter on the loop's timers has nothing to release."""
        self._closed = True
        tfd = self._tfd
        if tfd is None or tfd.fd < 0:
            return
        loop = self._loop
        if not loop.is_closed():
            with contextlib.suppress(Exception):
                loop.remove_reader(tfd.fd)
        tfd.close()
        self._fast_arm = None
        self._interval_ns = 0
        self._series_reader = None
        self._wakeup.fire()  # a wait in progress re-checks the clock and goes on with the loop's timers
        self._tfd = None
        self.mode = "loop-timer"  # a later wait still works, on the loop's timers
        if self._call is not None:  # so does a pending call_at
            self._arm(self._call_target, self._now())

    def __enter__(self) -> DeadlineWaiter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Clock:
    """Monotonic seconds plus sleeping until an absolute deadline on the same time base.

    ``now`` is a plain callable attribute (not a method) so hot paths can bind it once: ``now = clock.now``.
    """

    __slots__ = ("_loop", "is_virtual", "now")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self.is_virtual: bool = bool(getattr(loop, "is_virtual_clock", False))
        self.now: Callable[[], float] = loop.time if self.is_virtual else time.monotonic

    async def sleep_until(self, deadline: float, wake: asyncio.Future[Any] | None = None) -> None:
        """Return at (never before) ``deadline`` on this clock, or as soon as ``wake`` is done.

        ``wake`` lets another thread or a signal handler cut the wait short (``Vehicle.stop()`` completes it
        with ``loop.call_soon_threadsafe``). This is a one-off wait on a fresh :class:`DeadlineWaiter`, closed
        on return; a task that waits again and again should keep its own waiter.
        """
        with DeadlineWaiter(self._loop) as waiter:
            await waiter.wait_until(deadline, wake)

    async def sleep(self, seconds: float) -> None:
        """Sleep ``seconds`` from now on this clock."""
        await self.sleep_until(self.now() + seconds)


def _set_done(fut: asyncio.Future[None], *_: object) -> None:
    if not fut.done():
        fut.set_result(None)


def get_clock(loop: asyncio.AbstractEventLoop | None = None) -> Clock:
    """The clock of ``loop`` (default: the running loop). Cached per loop, so calling it is cheap."""
    if loop is None:
        loop = asyncio.get_running_loop()
    clock = _CLOCKS.get(loop)
    if clock is None:
        # A clock holds its loop (its ``now`` is the virtual loop's ``time``), so the weak keys alone never let
        # a loop go: the clocks of closed loops are dropped whenever a new loop's is made. A program that runs
        # one loop after another (a test suite, a benchmark) keeps only the loops still open.
        for old in [key for key in _CLOCKS if key.is_closed()]:
            del _CLOCKS[old]
        clock = _CLOCKS[loop] = Clock(loop)
    return clock


_CLOCKS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Clock] = weakref.WeakKeyDictionary()
