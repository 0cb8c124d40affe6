"""The pieces of one drive's state, each with one job: what :class:`~asyncdonkey.core.drive.Drive` is made of.

Why pieces. A drive keeps a lot: what it was asked for, its counters, its stop request, the work it owns beside the
ticks, its rate-limited complaints about parts. Held as some forty attributes of one object, every reader had to
know all of them to find the four it needed. Grouped by role, each piece says what it is for, and the code that
reads one piece (the report, shutdown, the stop request) names only that one.

Why no cost. The tick binds the pieces it writes (the counters, the stop latch) to fast locals once, when its
generator starts; writing ``counters.loops`` then costs what writing ``self.loops`` did: one attribute store on a
local. The pieces are slotted, so those stores go to a fixed place in the object, not into a dict.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ..ratelimit import LogThrottle

if TYPE_CHECKING:
    from ..errors import PartError
    from ..safety.activity import LoopActivity
    from .partrun import PartRun
    from .pipeline import Pipeline, Reaction, ReentryGuard
    from .plan import Entry

__all__ = ["BackgroundWork", "DriveLog", "DriveSettings", "StopLatch", "TickCounters"]

logger = logging.getLogger("asyncdonkey.loop")


@dataclass(frozen=True, slots=True)
class DriveSettings:
    """What ``Vehicle.run()`` asked of this drive besides its rate and limits; fixed for the whole drive."""

    #: after a stop request, an awaited part that has not returned within this is cancelled
    stop_grace_s: float = 1.0
    #: a sync part holding the loop thread longer than this is named in a warning when it returns
    block_report_s: float = 0.25
    #: spin the last stretch before each deadline (``asyncdonkey.clock.DeadlineWaiter``)
    precise: bool = False
    #: ``Vehicle.safety_process``: None starts the safety process when it can, True requires it, False never
    want_safety_process: bool | None = None
    #: the exit grace the safety process enforces while the car's signal handlers are installed (else None)
    exit_grace_s: float | None = None


class TickCounters:
    """The drive's timing state, written by the tick and read by the report (and by parts reporting on the loop
    while it runs, through ``Drive.loops`` and its neighbours): kept on an object, not in the tick's locals, so
    that whatever ends the drive can fill the report from them."""

    __slots__ = ("first_start", "last_end", "last_start", "loops", "overruns", "skipped", "t0")

    def __init__(self) -> None:
        #: the first tick's deadline (None: at once), fixed when the background work starts
        self.t0: float | None = None
        #: ticks run, ticks longer than a period, deadlines skipped because the loop was more than a period behind
        self.loops = 0
        self.overruns = 0
        self.skipped = 0
        #: the first and the latest tick's start, the latest tick's end
        self.first_start = 0.0
        self.last_start = 0.0
        self.last_end = 0.0


class StopLatch:
    """The drive's stop request, and the grace that makes it end an awaited part that does not return.

    :meth:`request` is safe from any thread and from a signal handler: it sets the latch and hands the rest to the
    loop thread, which wakes a drive waiting for a deadline and, while the drive ticks, arms the grace. The grace
    cancels the drive task only while it awaits a part's call (:attr:`awaiting`); the tick then counts that part's
    call as cut short and the stop goes on."""

    __slots__ = (
        "_activity",
        "_grace_handle",
        "_grace_s",
        "_loop",
        "awaiting",
        "grace_cancel",
        "reason",
        "requested",
        "task",
        "wake",
    )

    def __init__(self, loop: asyncio.AbstractEventLoop, grace_s: float, activity: LoopActivity) -> None:
        self._loop = loop
        self._grace_s = grace_s
        #: what the loop thread is doing (the drive): whether it ticks, the part being called
        self._activity = activity
        self.requested = False
        #: why the drive ended: set by the request, a limit, an error (the first one kept where it matters)
        self.reason = ""
        #: a future the drive waits on between ticks, completed by a request (one per drive)
        self.wake: asyncio.Future[None] | None = None
        self._grace_handle: asyncio.TimerHandle | None = None
        #: the awaitable of the part call the drive task is awaiting (None: none)
        self.awaiting: Any = None
        #: the drive task was cancelled by the grace (not by its caller)
        self.grace_cancel = False
        #: the task that ticks (what the grace cancels)
        self.task: asyncio.Task[Any] | None = None

    def request(self, reason: str) -> None:
        """Stop after the current tick. Safe from any thread and from a signal handler."""
        if not self.requested:
            self.requested = True
            self.reason = self.reason or reason
        loop = self._loop
        if not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._on_request)
            except RuntimeError:  # the loop closed in between
                pass

    def _on_request(self) -> None:
        w = self.wake
        if w is not None and not w.done():
            w.set_result(None)
        # an awaited part that does not return within the grace is cancelled, so a stop always ends the tick
        if self._grace_handle is None and self._activity.on:
            self._grace_handle = self._loop.call_later(self._grace_s, self._cancel_awaited_part)

    def _cancel_awaited_part(self) -> None:
        """Interrupt an awaited part that outlived the stop grace by cancelling the drive task at its await."""
        task = self.task
        if self.awaiting is not None and task is not None and not task.done():
            current = self._activity.current
            name = current.name if current is not None else "?"
            logger.error("part %r did not return within %.1f s of the stop request: cancelling it", name, self._grace_s)
            self.grace_cancel = True
            task.cancel()


class BackgroundWork:
    """The work a drive owns beside its ticks, which shutdown takes down: the parts' ``update()`` tasks and threads,
    the worker pool of offloaded calls, the pipelines, the push sources and their reactions, the re-entry guards;
    and what became of it (the first failure that stops the car, the parts left running)."""

    __slots__ = (
        "abandoned",
        "error",
        "executor",
        "pipelines",
        "push_sources",
        "reentry_guards",
        "tasks",
        "threads",
        "unsubscribe",
    )

    def __init__(self) -> None:
        self.tasks: list[tuple[Entry, asyncio.Task[Any]]] = []
        self.threads: list[tuple[Entry, threading.Thread]] = []
        #: made on first use (:meth:`get_executor`), shut down and dropped by shutdown
        self.executor: concurrent.futures.ThreadPoolExecutor | None = None
        #: the failure of background work that stops the car (``on_error="stop"``), raised by ``Vehicle.run()``
        self.error: PartError | None = None
        #: pipelined parts (``asyncdonkey.core.pipeline``): the tick calls their kickers in their place
        self.pipelines: list[Pipeline] = []
        #: push sources: (the part's run, its ``subscribe``, the reactions it starts)
        self.push_sources: list[tuple[PartRun, Any, Reaction | None]] = []
        #: what undoes each subscription, called when the ticks end
        self.unsubscribe: list[Any] = []
        #: the parts more than one path can be inside at once, one call at a time (``asyncdonkey.core.pipeline``)
        self.reentry_guards: list[ReentryGuard] = []
        #: parts whose shutdown() or update() thread did not finish in time (left running as daemon threads)
        self.abandoned: list[str] = []

    def get_executor(self) -> concurrent.futures.ThreadPoolExecutor:
        if self.executor is None:
            self.executor = concurrent.futures.ThreadPoolExecutor(
                max_workers=4, thread_name_prefix="asyncdonkey-offload"
            )
        return self.executor

    def unsubscribe_push_sources(self) -> None:
        for unsubscribe in self.unsubscribe:
            if callable(unsubscribe):
                unsubscribe()
        self.unsubscribe.clear()


class DriveLog:
    """What the drive says about parts that misbehave, rate-limited so that a 1 kHz loop cannot flood its log: a
    part's errors, a sync part holding the loop thread (the longest hold kept for the report), ticks overrunning
    their period (``verbose``)."""

    __slots__ = ("_blocks", "_errors", "_jitter", "longest_block")

    def __init__(self) -> None:
        self._errors = LogThrottle(1.0)
        self._blocks = LogThrottle(1.0)
        self._jitter = LogThrottle(1.0)
        #: ``(seconds, part)`` of the longest hold of the loop thread past ``block_report_s`` (None: none)
        self.longest_block: tuple[float, str] | None = None

    def error_ready(self, name: str, now: float) -> str | None:
        """Whether part ``name``'s error may be logged now: ``None`` (held back), or the message's suffix."""
        return self._errors.ready(name, now, "more errors")

    def blocked(self, name: str, blocked: float, now: float) -> None:
        """A sync part held the loop thread past the failsafe window: name it (the watchdog covered the car)."""
        if self.longest_block is None or blocked > self.longest_block[0]:
            self.longest_block = (blocked, name)
        more = self._blocks.ready(name, now)
        if more is not None:
            logger.warning(
                "loop blocked %s ms by part %r (a sync run() on the loop thread; add it with executor=True if it "
                "can block)%s",
                f"{blocked * 1e3:,.0f}",
                name,
                more,
            )

    def overrun(self, over: float, end: float) -> None:
        """``verbose=True``: a tick took ``over`` seconds more than its period."""
        more = self._jitter.ready("jitter", end)
        if more is not None:
            logger.warning("jitter violation in vehicle loop with %.0f ms overrun%s", over * 1e3, more)
