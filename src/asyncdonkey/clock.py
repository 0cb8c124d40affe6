"""The one clock the runtime reads.

Every duration, deadline and timestamp in asyncdonkey comes from a :class:`Clock` taken from the event loop
the code runs on (DESIGN.md §3.1). On a :class:`~asyncdonkey.testing.VirtualClockLoop` the clock *is* the
loop's virtual time, so a test controls everything the runtime measures. On a real loop the clock reads
``time.monotonic()`` (nanosecond resolution on Linux) rather than ``loop.time()``, because uvloop's
``loop.time()`` only has millisecond resolution; sleeping still goes through the loop's timers.

Wall-clock time (``time.time()``) is used only where a human or a file needs it, e.g. ``_timestamp_ms`` in
recorded records.
"""

from __future__ import annotations

import asyncio
import time
import weakref
from collections.abc import Callable

__all__ = ["Clock", "get_clock"]

#: Below this, a real-loop sleep finishes by yielding instead of arming a timer: uvloop timers round to
#: whole milliseconds, so a sub-millisecond timer can fire a full millisecond late (or early).
_SPIN_BELOW_S = 0.0011


class Clock:
    """Monotonic seconds plus sleeping until an absolute deadline on the same time base.

    ``now`` is a plain callable attribute (not a method) so hot paths can bind it once: ``now = clock.now``.
    """

    __slots__ = ("_loop", "is_virtual", "now")

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self.is_virtual: bool = bool(getattr(loop, "is_virtual_clock", False))
        self.now: Callable[[], float] = loop.time if self.is_virtual else time.monotonic

    async def sleep_until(self, deadline: float, wake: asyncio.Future[None] | None = None) -> None:
        """Return at (never before) ``deadline`` on this clock, or as soon as ``wake`` is done.

        ``wake`` lets another thread or a signal handler cut the wait short (``Vehicle.stop()`` completes it
        with ``loop.call_soon_threadsafe``). On the virtual loop the timer is armed at exactly ``deadline`` so
        no float error accumulates. On a real loop we sleep on the loop's timer until just before the
        deadline and then yield until it has passed, which keeps lateness well under a millisecond on
        uvloop, whose timers round to whole milliseconds.
        """
        loop = self._loop
        if self.is_virtual:
            if deadline <= loop.time():
                await asyncio.sleep(0)
                return
            fut = wake if wake is not None else loop.create_future()
            handle = loop.call_at(deadline, _set_done, fut)
            try:
                await fut
            finally:
                handle.cancel()
            return
        now = time.monotonic
        remaining = deadline - now()
        while remaining > _SPIN_BELOW_S:
            if wake is not None and wake.done():
                return
            fut = loop.create_future()
            handle = loop.call_later(remaining - _SPIN_BELOW_S, _set_done, fut)
            if wake is not None:
                wake.add_done_callback(lambda _w, f=fut: _set_done(f))
            try:
                await fut
            finally:
                handle.cancel()
            remaining = deadline - now()
        while now() < deadline:
            if wake is not None and wake.done():
                return
            await asyncio.sleep(0)

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
        clock = _CLOCKS[loop] = Clock(loop)
    return clock


_CLOCKS: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, Clock] = weakref.WeakKeyDictionary()
