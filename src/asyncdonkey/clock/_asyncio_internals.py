"""Every CPython implementation detail the virtual clock relies on, in one place, checked at import.

:class:`~asyncdonkey.clock.virtual_loop.VirtualClockLoop` needs to see things asyncio and the threading modules keep
private: the loop's timer heap (``_scheduled``), its ready queue (``_ready``), what one loop iteration does
(``_run_once``), the fields of a timer handle, how ``asyncio.wrap_future`` creates its future, how a
``ThreadPoolExecutor`` worker runs a job, which frames a thread is in while it blocks on a lock, and the
``threading`` module's tables of threads. They have been stable from Python 3.8 to 3.13, but none is promised.
Everything that touches them lives here, and :func:`problems` checks each one against the running Python:
the virtual loop refuses to start (and ``tests/core/test_asyncio_internals.py`` fails) with a message naming
what changed, rather than mis-timing silently.
"""

from __future__ import annotations

import asyncio
import concurrent.futures.thread as _cf_thread
import contextvars
import heapq
import inspect
import threading
import time
from asyncio import base_events, events, futures
from collections.abc import Callable, Sequence
from types import CodeType, FrameType
from typing import TYPE_CHECKING, Any, Protocol

__all__ = [
    "WRAP_FUTURE",
    "LoopIteration",
    "SeqTimerHandle",
    "idle_pool_worker",
    "newest_thread",
    "next_live_timer",
    "problems",
    "push_timer",
    "queue_callback",
    "ready_tasks",
    "schedule_timer",
    "thread_count",
    "waiting",
]

# -- timers and the ready queue ------------------------------------------------------------------------------


class _LoopFields(Protocol):
    """The private fields of an asyncio loop a handle's ``cancel`` reads (for the type checker only)."""

    _debug: bool
    _timer_cancelled_count: int


if TYPE_CHECKING:
    # asyncio's private handle fields, which typeshed's stubs leave out: declared for the type checker only, so the
    # handles built field by field below are checked; at run time the classes are asyncio's own (the else branch)

    class _HandleFields(events.Handle):
        _callback: Callable[..., object] | None
        _args: Sequence[Any] | None  # type: ignore[assignment]  # (stub: never None; asyncio's cancel sets None)
        _loop: _LoopFields
        _source_traceback: list[Any] | None
        _repr: str | None
        _context: contextvars.Context

    class _TimerHandleFields(events.TimerHandle, _HandleFields):
        _when: float
        _scheduled: bool

    _TimerHandle = _TimerHandleFields
    _Handle = _HandleFields
else:
    _TimerHandle = events.TimerHandle
    _Handle = events.Handle


class SeqTimerHandle(_TimerHandle):
    """A timer handle ordered by (deadline, scheduling sequence), so timers with equal deadlines fire FIFO.

    asyncio's heap compares handles with ``<``; ours never mixes with plain handles (every timer of the
    virtual loop is made by its ``call_at``), so the comparison skips the type check.
    """

    __slots__ = ("_seq",)

    def __init__(
        self,
        seq: int,
        when: float,
        callback: Callable[..., Any],
        args: tuple[Any, ...],
        loop: asyncio.AbstractEventLoop,
        context: Any = None,
    ) -> None:
        super().__init__(when, callback, args, loop, context)
        self._seq = seq

    def cancel(self) -> None:
        """``TimerHandle.cancel`` in one call instead of four (a timer is cancelled after it fires on nearly every
        tick: ``asyncio.sleep`` and the drive's waits do so); :func:`problems` checks it against asyncio's."""
        if self._cancelled:
            return
        loop = self._loop
        if loop._debug:  # asyncio's, which keeps the handle's repr for its slow-callback warnings
            super().cancel()
            return
        if self._scheduled:
            loop._timer_cancelled_count += 1  # what loop._timer_handle_cancelled(self) does
        self._cancelled = True
        self._callback = None
        self._args = None

    def __lt__(self, other: Any) -> bool:
        a: float
        b: float  # (bare annotations: no code, the comparison runs for every timer pushed or popped)
        a, b = self._when, other._when
        return a < b or (a == b and self._seq < other._seq)

    def __le__(self, other: Any) -> bool:
        a: float
        b: float
        a, b = self._when, other._when
        return a < b or (a == b and self._seq <= other._seq)


_new_timer = SeqTimerHandle.__new__
_new_handle = events.Handle.__new__
_copy_context = contextvars.copy_context
_heappush = heapq.heappush


def schedule_timer(
    loop: Any, seq: int, when: float, callback: Callable[..., Any], args: tuple[Any, ...], context: Any
) -> SeqTimerHandle:
    """``call_at`` of a loop not in debug mode: a new timer, into the heap, marked as scheduled.

    It sets the handle's fields itself rather than through ``TimerHandle.__init__`` (which calls
    ``Handle.__init__``, which asks the loop for its debug flag): a third of the cost of a timer, paid on every
    tick. :func:`problems` checks that a handle made here has exactly the fields asyncio's would. In debug
    mode the loop builds its timers the asyncio way, which records where each was created.
    """
    if loop._closed:
        loop._check_closed()  # raises, with asyncio's message
    timer = _new_timer(SeqTimerHandle)
    timer._callback = callback
    timer._args = args
    timer._cancelled = False
    timer._loop = loop
    timer._source_traceback = None
    timer._repr = None
    timer._context = _copy_context() if context is None else context
    timer._when = when
    timer._seq = seq
    _heappush(loop._scheduled, timer)
    timer._scheduled = True
    return timer


def queue_callback(loop: Any, callback: Callable[..., Any], args: tuple[Any, ...], context: Any) -> events.Handle:
    """``call_soon`` of a loop not in debug mode: a handle, field by field as in :func:`schedule_timer`, at the
    end of the ready queue. Every task step and every future's callback is queued through here."""
    if loop._closed:
        loop._check_closed()  # raises, with asyncio's message
    handle = _new_handle(_Handle)
    handle._callback = callback
    handle._args = args
    handle._cancelled = False
    handle._loop = loop
    handle._source_traceback = None
    handle._repr = None
    handle._context = _copy_context() if context is None else context
    loop._ready.append(handle)
    return handle


def push_timer(loop: Any, timer: SeqTimerHandle) -> None:
    """What ``BaseEventLoop.call_at`` does with a new timer: into the heap, marked as scheduled."""
    if timer._source_traceback:
        del timer._source_traceback[-1]
    heapq.heappush(loop._scheduled, timer)
    timer._scheduled = True


def next_live_timer(loop: Any) -> float | None:
    """The deadline of the earliest timer that is not cancelled (cancelled ones at the head are dropped, as
    ``_run_once`` would), or ``None`` when no timer is left."""
    scheduled = loop._scheduled
    while scheduled and scheduled[0]._cancelled:
        loop._timer_cancelled_count -= 1
        heapq.heappop(scheduled)._scheduled = False
    return scheduled[0]._when if scheduled else None


def has_ready(loop: Any) -> bool:
    """Whether a callback is queued to run (a thread's ``call_soon_threadsafe`` may add one at any time)."""
    return bool(loop._ready)


def ready_tasks(loop: Any) -> list[asyncio.Task[Any]]:
    """The tasks whose next step is queued in the ready queue (the tasks that keep the loop busy)."""
    tasks = []
    for handle in list(loop._ready):
        owner = getattr(getattr(handle, "_callback", None), "__self__", None)
        if isinstance(owner, asyncio.Task) and owner not in tasks:
            tasks.append(owner)
    return tasks


# asyncio's rule for rebuilding the heap (its values since Python 3.5, should the names ever go: see problems())
_MIN_SCHEDULED: int = getattr(base_events, "_MIN_SCHEDULED_TIMER_HANDLES", 100)
_MIN_CANCELLED_FRACTION: float = getattr(base_events, "_MIN_CANCELLED_TIMER_HANDLES_FRACTION", 0.5)
_heappop = heapq.heappop


class LoopIteration:
    """``BaseEventLoop._run_once`` for a loop that decides itself when to poll for I/O and when time moves.

    asyncio's iteration computes a select timeout from the clock, calls ``selector.select(timeout)`` and reads
    the clock again; a virtual loop only needs to know which case it is in. Here the case picks the hook:
    ``_poll_busy()`` when callbacks are ready (or the loop is stopping, or the earliest timer is already due:
    asyncio's timeout 0), ``_poll_idle()`` when everything waits (asyncio's timeout > 0, or ``None`` with no
    timer). Each returns the selector events to process (an empty sequence for none) and may move the clock.
    The rest is asyncio's iteration: cancelled timers are dropped by the same rule, due timers join the ready
    queue in deadline order, and the callbacks ready at the start of this step run, in order. The clock is the
    loop's own ``_virtual_time`` attribute (read directly: this runs every iteration).

    In debug mode the loop runs asyncio's own iteration (it times callbacks and warns about slow ones); the
    loop's selector then routes ``select(timeout)`` to the same two hooks.
    """

    __slots__ = ()

    def _run_once(self: Any) -> None:
        if self._debug:
            super()._run_once()  # type: ignore[misc]
            return
        scheduled = self._scheduled
        n = len(scheduled)
        if n > _MIN_SCHEDULED and self._timer_cancelled_count / n > _MIN_CANCELLED_FRACTION:
            _drop_cancelled(self)
            scheduled = self._scheduled
        else:
            while scheduled and scheduled[0]._cancelled:
                self._timer_cancelled_count -= 1
                _heappop(scheduled)._scheduled = False
        ready = self._ready
        if ready or self._stopping:
            event_list = self._poll_busy()
        elif not scheduled:
            event_list = self._poll_idle(None)
        else:
            when = scheduled[0]._when
            event_list = self._poll_busy() if when <= self._virtual_time else self._poll_idle(when)
        if event_list:
            self._process_events(event_list)
        if scheduled:
            end = self._virtual_time + self._clock_resolution
            while scheduled and scheduled[0]._when < end:
                handle = _heappop(scheduled)
                handle._scheduled = False
                ready.append(handle)
        for _ in range(len(ready)):
            handle = ready.popleft()
            if not handle._cancelled:
                handle._run()
        handle = None  # no cycle through a handle whose callback raised


def _drop_cancelled(loop: Any) -> None:
    """Rebuild the timer heap without its cancelled timers (asyncio does so when they are over half of it)."""
    live = []
    for handle in loop._scheduled:
        if handle._cancelled:
            handle._scheduled = False
        else:
            live.append(handle)
    heapq.heapify(live)
    loop._scheduled = live
    loop._timer_cancelled_count = 0


def newest_thread() -> threading.Thread | None:
    """The thread registered last in ``threading``'s table of running threads (a starting thread is added at
    the end). Beside :func:`thread_count` it tells a census that a thread started since, even if another one
    ended meanwhile and the count is the same."""
    return next(reversed(threading._active.values()), None)  # type: ignore[attr-defined]


def thread_count() -> int:
    """``threading.active_count()`` without taking the threads' lock (a fifth of the cost; it runs every loop
    iteration). Reading the two tables unlocked can count a thread moving from "starting" to "running" twice,
    never zero times: at worst one needless census."""
    return len(threading._active) + len(threading._limbo)  # type: ignore[attr-defined]


# -- executor futures and what threads are doing -------------------------------------------------------------
#
# Only code objects and line numbers are read here, never a frame's locals: on Python <= 3.12 reading
# ``frame.f_locals`` of another thread's frame stores a snapshot of its variables in the frame, keeping them
# alive (a TFLite interpreter then refuses to run while a view of its buffers is still referenced).

_WRAP_FUTURE: CodeType = futures.wrap_future.__code__
_POOL_WORKER: CodeType = _cf_thread._worker.__code__
_CONDITION_WAIT: CodeType = threading.Condition.wait.__code__
_THREAD_JOIN: CodeType = threading.Thread.join.__code__
_TSTATE_LOCK_WAIT: CodeType | None = getattr(getattr(threading.Thread, "_wait_for_tstate_lock", None), "__code__", None)


def _untimed_acquire_line() -> int | None:
    """The line of ``Condition.wait`` that blocks without a timeout: ``waiter.acquire()`` under
    ``if timeout is None:`` (a wait with a timeout blocks on another line)."""
    try:
        lines, first = inspect.getsourcelines(threading.Condition.wait)
    except (OSError, TypeError):
        return None
    for i in range(len(lines) - 1):
        if lines[i].strip() == "if timeout is None:" and lines[i + 1].strip() == "waiter.acquire()":
            return first + i + 1
    return None


_UNTIMED_ACQUIRE_LINE = _untimed_acquire_line()


#: the code object of ``asyncio.wrap_future``: a ``loop.create_future`` called from it is executor work on its way
#: to the loop, through ``run_in_executor`` or directly (``wrap_future(pool.submit(...))``). The virtual loop
#: compares its caller's code object with it inline (it runs every tick).
WRAP_FUTURE = _WRAP_FUTURE


def idle_pool_worker(frame: FrameType) -> bool:
    """Whether a thread's innermost frame is a ``ThreadPoolExecutor`` worker waiting for its next job."""
    return frame.f_code is _POOL_WORKER


def waiting(frame: FrameType) -> str | None:
    """How a thread whose innermost frame is ``frame`` is waiting: ``"blocked"`` when only another thread (or
    the loop) can end the wait, ``"timed"`` when it ends by itself too, ``None`` when it is not waiting on a
    ``threading`` primitive (it computes, sleeps, or blocks in I/O: it looks busy).

    ``threading.Condition.wait`` is where ``Event.wait``, ``Queue.get``, ``Semaphore.acquire``, ``Barrier.wait``
    and ``concurrent.futures.Future.result`` block; ``Thread.join`` waits for another thread, whose own state
    says whether it works (so a join counts as blocked, with or without a timeout).
    """
    code = frame.f_code
    if code is _CONDITION_WAIT:
        return "blocked" if frame.f_lineno == _UNTIMED_ACQUIRE_LINE else "timed"
    if code is _THREAD_JOIN or code is _TSTATE_LOCK_WAIT:
        return "blocked"
    return None


# -- the checks ---------------------------------------------------------------------------------------------


def problems() -> list[str]:
    """What this module relies on and this Python no longer provides; empty when all is well."""
    found: list[str] = []
    loop = asyncio.SelectorEventLoop()
    try:
        for name, kind in (("_scheduled", list), ("_timer_cancelled_count", int), ("_clock_resolution", float)):
            if not isinstance(getattr(loop, name, None), kind):
                found.append(f"asyncio event loops have no {kind.__name__} {name}")
        if not hasattr(getattr(loop, "_ready", None), "popleft"):
            found.append("asyncio event loops have no deque _ready")
        for name in ("_check_closed", "_check_thread", "_check_callback", "_make_subprocess_transport", "_selector"):
            if not hasattr(loop, name):
                found.append(f"asyncio selector event loops have no {name}")
        handle = SeqTimerHandle(0, 1.0, print, (), loop)
        for name in ("_when", "_cancelled", "_scheduled", "_callback", "_source_traceback"):
            if not hasattr(handle, name):
                found.append(f"asyncio.TimerHandle has no {name}")
        for name in ("_stopping", "_closed", "_debug", "_process_events"):
            if not hasattr(loop, name):
                found.append(f"asyncio selector event loops have no {name}")
        found += _handle_problems(loop)
    finally:
        loop.close()
    for name in ("_MIN_SCHEDULED_TIMER_HANDLES", "_MIN_CANCELLED_TIMER_HANDLES_FRACTION"):
        if not hasattr(base_events, name):
            found.append(f"asyncio.base_events has no {name} (when _run_once rebuilds its timer heap)")
    if "_run_once" not in base_events.BaseEventLoop.run_forever.__code__.co_names:
        found.append("BaseEventLoop.run_forever no longer calls _run_once")
    if not hasattr(events.Handle, "_run"):
        found.append("asyncio.Handle has no _run")
    if not all(isinstance(getattr(threading, name, None), dict) for name in ("_active", "_limbo")):
        found.append("threading no longer keeps its threads in the dicts _active and _limbo")
    elif thread_count() != threading.active_count():
        found.append("threading.active_count() no longer counts threading._active and threading._limbo")
    else:
        found += _newest_thread_problems()
    run_once = getattr(base_events.BaseEventLoop, "_run_once", None)
    names = run_once.__code__.co_names if run_once is not None else ()
    for name in ("_scheduled", "_ready", "_selector", "select", "_timer_cancelled_count"):
        if name not in names:
            found.append(f"BaseEventLoop._run_once no longer uses {name}")
    if "create_future" not in _WRAP_FUTURE.co_names:
        found.append("asyncio.wrap_future no longer calls loop.create_future()")
    if "work_queue" not in _POOL_WORKER.co_varnames:
        found.append("concurrent.futures.thread._worker no longer waits on a work_queue")
    if _UNTIMED_ACQUIRE_LINE is None:
        found.append("threading.Condition.wait no longer blocks in 'waiter.acquire()' under 'if timeout is None:'")
    return found


def _newest_thread_problems() -> list[str]:
    """Whether a thread that starts is the newest in ``threading._active`` while it runs."""
    release = threading.Event()
    thread = threading.Thread(target=release.wait, name="asyncdonkey internals check", daemon=True)
    thread.start()
    try:
        deadline = 200  # start() may return before the thread moved from threading._limbo to _active
        while thread.ident not in threading._active and deadline:  # type: ignore[attr-defined]
            time.sleep(0.001)
            deadline -= 1
        newest = newest_thread()
    finally:
        release.set()
        thread.join()
    return [] if newest is thread else ["threading._active no longer lists a starting thread last"]


def _handle_problems(loop: Any) -> list[str]:
    """Whether :func:`schedule_timer` and :func:`queue_callback` set exactly the fields asyncio's ``call_at`` and
    ``call_soon`` set, to the same values, and whether cancelling such a timer does what asyncio's cancel does."""
    found = []
    context = contextvars.copy_context()
    pairs: tuple[tuple[str, Callable[[], events.Handle], Callable[[], events.Handle]], ...] = (
        (
            "TimerHandle",
            lambda: schedule_timer(loop, 0, 1.0, print, (2,), context),
            lambda: loop.call_at(1.0, print, 2, context=context),
        ),
        (
            "Handle",
            lambda: queue_callback(loop, print, (2,), context),
            lambda: loop.call_soon(print, 2, context=context),
        ),
    )
    missing = object()

    def differ(ours: Any, theirs: Any) -> list[str]:
        names = {n for cls in type(theirs).__mro__ for n in getattr(cls, "__slots__", ()) if n != "__weakref__"}
        return sorted(n for n in names if getattr(ours, n, missing) != getattr(theirs, n, missing))

    for kind, make_ours, make_theirs in pairs:
        try:
            ours = make_ours()
        except (AttributeError, TypeError) as exc:
            found.append(f"an asyncio.{kind} cannot be built field by field: {exc}")
            continue
        theirs = make_theirs()
        fields = differ(ours, theirs)
        if fields:
            found.append(
                f"asyncio.{kind} has fields the virtual loop does not set as asyncio does: {', '.join(fields)}"
            )
        if kind == "TimerHandle" and isinstance(ours, SeqTimerHandle):  # (always, as schedule_timer makes it)
            count = loop._timer_cancelled_count
            theirs.cancel()
            counted = loop._timer_cancelled_count - count
            SeqTimerHandle.cancel(ours)
            fields = differ(ours, theirs)
            if fields or loop._timer_cancelled_count - count != 2 * counted:
                found.append(
                    f"asyncio.TimerHandle.cancel does what the virtual loop's timers do not: {', '.join(fields)}"
                )
            loop._scheduled.clear()
            loop._timer_cancelled_count = 0
        else:
            loop._ready.clear()
    return found
