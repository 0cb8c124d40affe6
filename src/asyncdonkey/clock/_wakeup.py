"""A reusable awaitable for one waiting task: what an ``asyncio.Future`` does for a wait, minus the Future.

Part of the clock's :class:`~asyncdonkey.clock.DeadlineWaiter`: a wait on a real loop would otherwise allocate a
Future per wait, and completing it would schedule the task's wake-up as one more callback for the next loop pass.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

__all__ = ["Wakeup"]


class Wakeup:
    """Speaks the Future protocol a Task needs (``_asyncio_future_blocking``, ``get_loop``, ``add_done_callback``,
    ``result``, ``cancel``; see :func:`asyncio.isfuture`) and is re-armed for every wait.

    :meth:`fire`, called from the timer's own loop callback, resumes the task in that same loop pass; a wake-up
    requested while a task is running (or a cancellation) goes through ``call_soon`` like a Future's would.
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
