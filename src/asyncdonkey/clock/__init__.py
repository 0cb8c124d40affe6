"""The one clock the runtime reads, the one deadline schedule every periodic task follows, and how to wait.

Every duration, deadline and timestamp in asyncdonkey comes from a :class:`Clock` taken from the event loop
the code runs on. On a :class:`~asyncdonkey.clock.virtual_loop.VirtualClockLoop` the clock *is* the loop's virtual time,
so a test controls everything the runtime measures. On a real loop the clock reads ``time.monotonic()``
(``CLOCK_MONOTONIC``, nanosecond resolution on Linux) rather than ``loop.time()``, because uvloop's
``loop.time()`` only has millisecond resolution.

This is the public module of the clock; each piece lives in a module of its own, re-exported here:

* :class:`Schedule` says *when*: tick ``k`` is due at ``t0 + k / rate_hz``; a tick that ends more than a period
  behind skips (and counts) the deadlines it missed instead of running them back to back (``_schedule``).
* :class:`TickGrid`, :func:`tick_grid` and :func:`grid_start`: a drive's ticks, known to its parts' background
  work so that their schedules fall on them (``_tick_grid``).
* :class:`DeadlineWaiter` says *how to wait* for an absolute deadline on the runtime clock, without spinning: a
  ``timerfd`` on Linux, the loop's own timers elsewhere, an exact loop timer on the virtual clock
  (``_deadline_waiter``; its reusable awaitable is ``_wakeup``).
* **Precise mode** (``DeadlineWaiter(precise=True)``, ``Vehicle.run(precise=True)``) trades CPU for tighter
  ticks: it sleeps to a learned spin window before the deadline and spins the rest on the clock, at most
  :data:`SPIN_BUDGET` of the time between deadlines, so that 99 % of the ticks start within
  :data:`PRECISE_TOLERANCE_S` (``_precise_wait``).

docs/timing.md says what each of them guarantees and costs, with the measurements behind precise mode's
constants. ``USE_TIMERFD = False`` (on this module) keeps new waiters off timerfd: the tests force the fallback
this way, and it is the escape hatch for a kernel or sandbox where timerfd misbehaves.

Wall-clock time (``time.time()``) is used only where a human or a file needs it, e.g. ``_timestamp_ms`` in
recorded records.
"""

from __future__ import annotations

import asyncio
import sys
import types
import weakref
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from . import _deadline_waiter
from ._deadline_waiter import DeadlineWaiter, WaitMode
from ._precise_wait import PRECISE_TOLERANCE_S, SPIN_BUDGET
from ._schedule import TICK_EPS, TIME_EPS, Schedule
from ._tick_grid import TICK_GRID, TickGrid, grid_start, tick_grid
from ._time_source import time_source

__all__ = [
    "PRECISE_TOLERANCE_S",
    "SPIN_BUDGET",
    "TICK_EPS",
    "TICK_GRID",
    "TIME_EPS",
    "Clock",
    "DeadlineWaiter",
    "Schedule",
    "TickGrid",
    "WaitMode",
    "get_clock",
    "grid_start",
    "tick_grid",
]

if TYPE_CHECKING:
    #: Whether new waiters may use a timerfd: ``_deadline_waiter.USE_TIMERFD``, read and set through this module.
    USE_TIMERFD: bool


class Clock:
    """Monotonic seconds plus sleeping until an absolute deadline on the same time base.

    ``now`` is a plain callable attribute (not a method) so hot paths can bind it once: ``now = clock.now``.
    """

    __slots__ = ("_loop", "is_virtual", "now")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        source = time_source(loop)
        self.is_virtual: bool = source.is_virtual
        self.now: Callable[[], float] = source.now

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


class _ClockModule(types.ModuleType):
    """This module, with ``USE_TIMERFD`` read from and written to the waiter's module, where waiters read it: the
    switch kept its documented place here when the waiter moved out."""

    @property
    def USE_TIMERFD(self) -> bool:
        return _deadline_waiter.USE_TIMERFD

    @USE_TIMERFD.setter
    def USE_TIMERFD(self, value: bool) -> None:
        _deadline_waiter.USE_TIMERFD = value


sys.modules[__name__].__class__ = _ClockModule
