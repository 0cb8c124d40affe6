"""The :class:`DeadlineWaiter`: waits for absolute deadlines on the runtime clock, reusing one OS timer.

Part of the clock (:mod:`asyncdonkey.clock` re-exports it). Three ways to wait, chosen per waiter
(:attr:`DeadlineWaiter.mode`):

- **timerfd** (Linux): a ``timerfd`` armed at the deadline on ``CLOCK_MONOTONIC`` (absolute, no slack) and
  watched by the running loop (``add_reader``; asyncio and uvloop alike). One timerfd per waiter, re-armed for
  every wait, closed by :meth:`DeadlineWaiter.close`. Late by the kernel's wake-up latency plus one loop pass,
  never early.
- **loop-timer** (elsewhere, or when a timerfd cannot be created): the loop's own timers, re-armed until the
  clock has passed the deadline, so never early either. uvloop's timers count whole milliseconds of a cached
  clock, so there the wait is armed one millisecond long.
- **virtual** (a :class:`~asyncdonkey.clock.virtual_loop.VirtualClockLoop`): an exact loop timer at the deadline, so
  runs are deterministic and free of float drift.

Precise mode's arithmetic (where to arm, and learning it) is the base class's, :mod:`asyncdonkey.clock._precise_wait`.
docs/timing.md has what each way costs and how late it wakes, as measured.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import weakref
from collections.abc import Callable
from math import ceil
from os import read as _read
from typing import Any, Literal

from . import _timerfd
from ._precise_wait import SHORT_SLEEP_MIN_S, PreciseWait
from ._time_source import time_source
from ._wakeup import Wakeup

__all__ = ["USE_TIMERFD", "DeadlineWaiter", "WaitMode"]

logger = logging.getLogger(__name__)

WaitMode = Literal["timerfd", "loop-timer", "virtual"]

#: How far a periodic timer's grid (``call_at(period=...)``) may fall behind the deadlines it stands for before it
#: is armed again on a new grid: it drifts by at most a nanosecond a period (see :meth:`DeadlineWaiter.call_at`).
_GRID_SLACK_NS = 2_000

#: Set to False to keep waits off timerfd (tests force the fallback this way; it is also the escape hatch for a
#: kernel or sandbox where timerfd misbehaves). ``asyncdonkey.clock.USE_TIMERFD`` is this same switch.
USE_TIMERFD = True


class DeadlineWaiter(PreciseWait):
    """Waits for absolute deadlines on the runtime clock, for one task at a time, reusing one OS timer.

    Create one per periodic task (the drive loop, a part's update loop), call :meth:`wait_until` for every
    deadline and :meth:`close` when done (or use it as a context manager). :attr:`mode` says which of the three
    ways in the module docstring this waiter uses.

    Args:
        loop: the event loop it waits on (default: the running loop).
        precise: arm the timer early by a learned spin window and spin the rest on the clock (see
            :attr:`spin_window_s`). Costs CPU for the window on every wait, at most ``SPIN_BUDGET`` (3 %) of the
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
        "_grid_ns",
        "_handle",
        "_interval_ns",
        "_loop",
        "_now",
        "_on_loop_timer_cb",
        "_on_wake_cb",
        "_series_reader",
        "_tfd",
        "_timer_slop",
        "_vfut",
        "_wakeup",
        "_watched",
        "mode",
        "waits",
    )

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None, *, precise: bool = False) -> None:
        loop = loop if loop is not None else asyncio.get_running_loop()
        is_virtual, now = time_source(loop)
        super().__init__(bool(precise) and not is_virtual)
        self._loop = loop
        self._now = now
        self._wakeup = Wakeup(loop)
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
        self._on_wake_cb = self._on_wake  # bound once: no bound-method object per wait
        self._on_loop_timer_cb = self._on_loop_timer
        #: Waits that actually slept (the deadline had not passed yet).
        self.waits = 0
        # uvloop's timers count whole milliseconds of a clock cached at the start of each loop pass: arm them
        # a millisecond long so they do not fire early (asyncio's own loop times with time.monotonic()).
        self._timer_slop = 0.0 if isinstance(loop, asyncio.BaseEventLoop) else 1e-3
        self.mode: WaitMode = "virtual" if is_virtual else "loop-timer"
        if not is_virtual and USE_TIMERFD and _timerfd.AVAILABLE:
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
            if t < target and (not self.precise or target - t >= SHORT_SLEEP_MIN_S):
                self._arm(target, t)
                return
            self._call = None
            if self.precise and not self._call_early:  # (an early callback reports its arrival: arrived())
                self._learn(t - target)
                spin_until = self._call_deadline
                now = self._now
                while t < spin_until:  # the last stretch is spun on the clock
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
                    if t >= target or (self.precise and target - t < SHORT_SLEEP_MIN_S):
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
        :attr:`_guard_s`), unless that leaves no room for a second sleep. Only precise mode learns from its first
        sleeps, so only there is one pending (:attr:`_first_at` stays 0 otherwise)."""
        if not self.precise:
            self._arm(target, now)
            return
        first = target - self._guard_s
        if first <= now + SHORT_SLEEP_MIN_S:
            first = target
        self._first_at = first
        self._arm(first, now)

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
        before the deadline (or up to :data:`SHORT_SLEEP_MIN_S` more, when the guard sleep woke too late for
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
            self._start_period(deadline, period)
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


def _set_done(fut: asyncio.Future[None], *_: object) -> None:
    if not fut.done():
        fut.set_result(None)
