"""Which time the runtime reads on a loop: the loop's own on the virtual clock, ``time.monotonic()`` elsewhere.

One definition, used by :class:`~asyncdonkey.clock.Clock` and by the
:class:`~asyncdonkey.clock.DeadlineWaiter` (which cannot import the clock module: the clock's one-off sleeps
are made with a waiter). On a real loop the runtime reads ``time.monotonic()`` (``CLOCK_MONOTONIC``, nanosecond
resolution on Linux) rather than ``loop.time()``, because uvloop's ``loop.time()`` only has millisecond
resolution.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import NamedTuple

__all__ = ["TimeSource", "time_source"]


class TimeSource(NamedTuple):
    """The runtime's time on one loop: whether it is the loop's virtual time, and the function that reads it."""

    is_virtual: bool
    now: Callable[[], float]


def time_source(loop: asyncio.AbstractEventLoop) -> TimeSource:
    """The runtime's time on ``loop`` (a :class:`~asyncdonkey.clock.virtual_loop.VirtualClockLoop` says it is virtual
    through ``loop.is_virtual_clock``)."""
    is_virtual = bool(getattr(loop, "is_virtual_clock", False))
    return TimeSource(is_virtual, loop.time if is_virtual else time.monotonic)
