"""Background loops that do something every so often: one :class:`~asyncdonkey.clock.Schedule`, one waiter.

A part's ``update()`` that pings a peer every half second, publishes a status every second or pushes health
figures to web pages would naturally be written ``while ...: work(); await clock.sleep(period)``. That drifts
(each period is the work plus the sleep) and opens, arms and closes a new OS timer for every sleep (a one-off
wait makes a :class:`~asyncdonkey.clock.DeadlineWaiter` of its own). :class:`Periodic` is the loop's timing
instead: deadlines ``t0 + k * period`` from the :class:`~asyncdonkey.clock.Schedule` the drive loop follows (no
drift; a loop that falls more than a period behind skips the deadlines it missed, counted, and never runs them
back to back), waited for with one :class:`~asyncdonkey.clock.DeadlineWaiter` kept for the loop's lifetime and
closed when it ends::

    with Periodic(0.5) as every:
        while not link.closed:
            link.ping()
            await every.next()

On the virtual clock the deadlines are exact loop timers, so such a loop is deterministic in tests.
"""

from __future__ import annotations

import asyncio
import math

from .clock import DeadlineWaiter, Schedule, get_clock

__all__ = ["Periodic"]


class Periodic:
    """Deadlines every ``period_s`` seconds from now, on the runtime clock of ``loop`` (default: the running one).

    Create it in the task that waits (it holds an OS timer of that task's loop), call :meth:`next` after each
    round of work, and :meth:`close` it when the loop ends (or use ``with``).
    """

    __slots__ = ("_now", "schedule", "waiter")

    def __init__(self, period_s: float, loop: asyncio.AbstractEventLoop | None = None) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"Periodic: period_s must be a positive finite number of seconds, got {period_s!r}")
        loop = loop if loop is not None else asyncio.get_running_loop()
        self._now = get_clock(loop).now
        #: The deadlines: tick 0 is now, tick ``k`` is due ``k`` periods later; ``schedule.skipped`` counts the
        #: deadlines missed because a round of work ran long.
        self.schedule = Schedule(1.0 / period_s, self._now())
        self.waiter = DeadlineWaiter(loop)

    async def next(self) -> int:
        """The current round of work has ended: wait for the next deadline. Returns the deadlines skipped.

        Deadlines missed by more than a period are skipped; a deadline already passed returns after one pass of
        the event loop, so a loop whose work outlasts its period still lets the other tasks run.
        """
        sched = self.schedule
        skipped = sched.advance(self._now())
        deadline = sched.deadline
        if self._now() < deadline:
            await self.waiter.wait_until(deadline)
        else:
            await asyncio.sleep(0)
        return skipped

    def close(self) -> None:
        """Release the OS timer (idempotent)."""
        self.waiter.close()

    def __enter__(self) -> Periodic:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
