"""Waiting in real time for something another thread, process or peer does: the suite's one polling helper.

A test that waits on the real clock for a car process, a socket peer, a browser or a chip model polls a condition
until it holds or a timeout passes. Each variant fails with one line that names what was waited for (``what``, or
the condition's own source line when none is given), how long, and the last value the condition returned, so a
timeout under load says what the car was doing instead of a bare ``assert False``.

* :func:`wait_until`: a blocking poll (``time.sleep`` between checks), for threads and processes;
* :func:`await_until`: the same inside a coroutine, yielding to the event loop between checks so the task that
  will make the condition true runs;
* :func:`time_when`: a blocking poll that returns the ``time.monotonic()`` reading at the first check the
  condition held, for tests that bound how long something took (a stopped pulse after ``kill -9``).

Every caller waits on the real clock, so its test is marked ``realtime`` (docs/testing.md). The deadline is
``time.monotonic()`` even inside a coroutine on the virtual clock, where ``loop.time()`` can jump.
"""

from __future__ import annotations

import asyncio
import inspect
import time
from collections.abc import Callable
from typing import TypeVar

__all__ = ["TimedOut", "await_until", "time_when", "wait_until"]

T = TypeVar("T")


class TimedOut(AssertionError):
    """The condition did not hold within the timeout (an ``AssertionError``, so pytest reports it as a failure)."""


def describe(cond: Callable[[], object]) -> str:
    """The condition's source line (``lambda: pca.pulse(0) == 370``) when it has one, else its repr: the default
    ``what``, so a timeout names the condition even when the caller did not."""
    try:
        return " ".join(inspect.getsource(cond).split())
    except (OSError, TypeError):
        return repr(cond)


What = str | Callable[[], str] | None
"""What was waited for: words, or a function giving them at the timeout (to name the state then), or ``None`` for
the condition's source line."""


def _timed_out(cond: Callable[[], object], timeout: float, what: What, last: object) -> TimedOut:
    named = what() if callable(what) else what or describe(cond)
    return TimedOut(f"timed out after {timeout:g} s waiting for {named}; last value: {last!r}")


def wait_until(cond: Callable[[], T], timeout: float = 5.0, what: What = None, step: float = 0.02) -> T:
    """Poll ``cond`` every ``step`` seconds until it returns something truthy, and return that; after ``timeout``
    seconds raise :class:`TimedOut` naming ``what`` and the last value seen."""
    deadline = time.monotonic() + timeout
    while True:
        got = cond()
        if got:
            return got
        if time.monotonic() > deadline:
            raise _timed_out(cond, timeout, what, got)
        time.sleep(step)


async def await_until(cond: Callable[[], T], timeout: float = 5.0, what: What = None, step: float = 0.005) -> T:
    """:func:`wait_until` for a coroutine: between checks it awaits ``asyncio.sleep(step)``, letting the loop's
    other tasks run (``step=0`` only yields, for a test on the virtual clock where a sleep would move time)."""
    deadline = time.monotonic() + timeout
    while True:
        got = cond()
        if got:
            return got
        if time.monotonic() > deadline:
            raise _timed_out(cond, timeout, what, got)
        await asyncio.sleep(step)


def time_when(cond: Callable[[], object], timeout: float, what: What = None, step: float = 0.001) -> float:
    """The ``time.monotonic()`` reading taken just before the first check at which ``cond`` held (so it is no
    later than the moment it was seen, within ``step`` of when it became true); :class:`TimedOut` after
    ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        now = time.monotonic()
        got = cond()
        if got:
            return now
        if now > deadline:
            raise _timed_out(cond, timeout, what, got)
        time.sleep(step)
