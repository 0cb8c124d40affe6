"""Ending a drive: safe state first, then everything else, none able to hold the process hostage.

Two phases, under one deadline:

1. **Safe state.** Every actuator (a part with ``safe_state_sync``, one added with ``actuator=True``, or one of
   Donkeycar's own actuator parts) is shut down at once and concurrently, before any other part: a camera
   whose ``shutdown()`` hangs must not delay the throttle's neutral by its timeout.
2. **The rest**, concurrently, each with its own ``shutdown_timeout``. A part whose ``shutdown`` takes a
   ``timeout`` keyword gets it (the tub writer drains for up to that long). Blocking shutdowns run on daemon
   threads, so one that hangs is logged and abandoned instead of keeping the process alive after the report.

Then background tasks are cancelled and ``update()`` threads joined, each bounded the same way.

Cancellation during shutdown is remembered, not swallowed: the safe-state phase still completes (it is bounded),
the rest is abandoned, and the caller re-raises ``CancelledError`` so an enclosing ``asyncio.timeout()`` works.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
import threading
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

if TYPE_CHECKING:
    from ..safety.watchdog import Watchdog
    from .drivestate import BackgroundWork
    from .plan import Entry

__all__ = ["in_daemon_thread", "shutdown_drive"]

logger = logging.getLogger("asyncdonkey.loop")
T = TypeVar("T")

#: extra time allowed to a part that bounds its own shutdown with the timeout we pass it
_SELF_BOUNDED_MARGIN_S = 0.5


class ShutdownScope(Protocol):
    """What shutdown takes down: the entries, the background work the drive owns (its tasks, threads and worker
    pool; the parts abandoned are noted there), its watchdog."""

    @property
    def entries(self) -> Sequence[Entry]: ...

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    @property
    def work(self) -> BackgroundWork: ...

    @property
    def watchdog(self) -> Watchdog | None: ...


def in_daemon_thread(
    loop: asyncio.AbstractEventLoop, fn: Callable[..., T], *args: Any, name: str = "asyncdonkey-shutdown", **kwargs: Any
) -> asyncio.Future[T]:
    """Run ``fn`` on a new daemon thread; the returned future resolves on ``loop`` with its result.

    Unlike an executor thread, a daemon thread that never returns does not keep the interpreter alive at exit.
    On the virtual clock the thread holds virtual time while it runs, as executor work does.
    """
    fut: asyncio.Future[T] = loop.create_future()

    def settle(ok: bool, value: Any) -> None:
        if fut.done():
            return
        if ok:
            fut.set_result(value)
        else:
            fut.set_exception(value)

    def target() -> None:
        try:
            result = fn(*args, **kwargs)
        except BaseException as exc:
            outcome: tuple[bool, Any] = (False, exc)
        else:
            outcome = (True, result)
        try:
            loop.call_soon_threadsafe(settle, *outcome)
        except RuntimeError:  # the loop is closed: nobody waits any more
            pass

    thread = threading.Thread(target=target, name=name, daemon=True)
    hold = getattr(loop, "hold_time_while", None)
    if hold is not None:
        release = hold(thread.is_alive, name)
        fut.add_done_callback(lambda _f: release())
    thread.start()
    return fut


async def _shutdown_one(e: Entry, loop: asyncio.AbstractEventLoop, abandoned: list[str]) -> None:
    plan = e.shutdown
    fn = plan.fn
    if fn is None:
        return
    kwargs = {"timeout": plan.timeout} if plan.takes_timeout else {}
    limit = plan.timeout + (_SELF_BOUNDED_MARGIN_S if kwargs else 0.0)
    try:
        if inspect.iscoroutinefunction(fn):
            await asyncio.wait_for(fn(**kwargs), limit)
        else:
            await asyncio.wait_for(in_daemon_thread(loop, fn, name=f"shutdown:{e.name}", **kwargs), limit)
    except TimeoutError:
        logger.error("part %r: shutdown() did not finish within %.1f s; abandoned", e.name, limit)
        abandoned.append(e.name)
    except asyncio.CancelledError:
        logger.error("part %r: shutdown() was cancelled", e.name)
    except Exception as exc:
        logger.error("part %r: shutdown() raised %r", e.name, exc, exc_info=exc)


async def _phase(
    entries: Iterable[Entry], loop: asyncio.AbstractEventLoop, abandoned: list[str], *, finish_on_cancel: bool
) -> bool:
    """Shut ``entries`` down concurrently; returns True if the caller's task was cancelled meanwhile."""
    tasks = [loop.create_task(_shutdown_one(e, loop, abandoned), name=f"shutdown:{e.name}") for e in entries]
    if not tasks:
        return False
    cancelled = False
    pending: set[asyncio.Task[None]] = set(tasks)
    while pending:
        try:
            _done, pending = await asyncio.wait(pending)
        except asyncio.CancelledError:
            cancelled = True
            if not finish_on_cancel:
                for t in pending:
                    t.cancel()
                break
    return cancelled


async def shutdown_drive(drive: ShutdownScope) -> bool:
    """Shut every part of ``drive`` down exactly once (module docstring). Returns True if cancelled meanwhile."""
    loop = drive.loop
    entries = [e for e in drive.entries if e.shutdown.fn is not None]
    work = drive.work
    abandoned = work.abandoned
    cancelled = await _phase([e for e in entries if e.actuator], loop, abandoned, finish_on_cancel=True)
    if drive.watchdog is not None:
        drive.watchdog.stop()
    if not cancelled:
        cancelled = await _phase([e for e in entries if not e.actuator], loop, abandoned, finish_on_cancel=False)
    for _, task in work.tasks:
        task.cancel()
    if not cancelled:
        for e, task in work.tasks:
            try:
                await asyncio.wait_for(task, e.shutdown.timeout)
            except asyncio.CancelledError:
                if not task.cancelled():  # we, not the task, were cancelled
                    cancelled = True
                    break
            except Exception:
                pass  # already reported by the task's done callback
        for e, t in work.threads:
            if cancelled:
                break
            try:
                await in_daemon_thread(loop, t.join, e.shutdown.timeout, name=f"join:{e.name}")
            except asyncio.CancelledError:
                cancelled = True
            if t.is_alive():
                abandoned.append(e.name)
                logger.error(
                    "part %r: update() thread still running %.1f s after shutdown(); abandoned (daemon thread)",
                    e.name,
                    e.shutdown.timeout,
                )
    if work.executor is not None:
        work.executor.shutdown(wait=False, cancel_futures=True)
        work.executor = None
    return cancelled
