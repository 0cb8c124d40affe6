"""An asyncio event loop on virtual time: hours of driving in a second, the same result every run.

Tests run on it, and so does ``asyncdonkey replay``, which plays a recording through a pilot at the recorded
times as fast as the CPU allows. Semantics follow Trio's ``MockClock`` with autojump: time moves only when
nothing is runnable, and then straight to the next timer's deadline, exactly, never backwards. A part that
awaits ``asyncio.sleep(0.08)`` costs exactly 80 ms of loop time.

How it works, and why this way:

* The loop is an :class:`asyncio.SelectorEventLoop` whose :meth:`time` returns a stored float. asyncio only
  blocks in ``selector.select(timeout)`` when its ready queue is empty, so "every task is waiting" is exactly
  "select would be called with a timeout > 0". There, if no real I/O is waiting, we set virtual time to the
  earliest live timer's deadline in one step. (Tools that patch the selector's timeout instead spend dozens of
  no-op loop cycles per jump.) The loop runs its own version of asyncio's iteration, which takes that decision
  directly instead of computing a timeout and calling ``select``: with nothing outside to watch, it reads no
  real clock and makes a system call only once in 64 iterations, so a timer and a jump cost less than one
  pass of plain asyncio's loop (``benchmarks/virtual_clock.py`` shows both). Its timers and callbacks are
  asyncio's handles, built field by field; :mod:`asyncdonkey.clock._asyncio_internals` checks every such shortcut
  against asyncio's own code paths.
* **Real work holds time still.** Virtual time must not run ahead of work that is really being done for the
  program, or a 1 s sleeper beside a 50 ms thread wakes first. So time stands still, and the loop waits in
  real time, while any of these is busy: executor work (``run_in_executor``, ``asyncio.to_thread``, and any
  ``asyncio.wrap_future`` of a ``concurrent.futures`` future, such as ``pool.submit(...)``); a non-daemon
  thread started after the loop was created; a subprocess started through the loop, until it exits; a
  ``hold_time_while(busy, name)`` hold (the tub writer's disk thread); the default executor's shutdown.
  Real work costs 0 virtual time. If holds last ``stall_timeout_s`` of real time, :class:`VirtualClockStall`
  names them.
* **Waiting is not working.** A thread blocked without a timeout in ``threading.Condition.wait`` (so in
  ``Event.wait()``, ``Queue.get()``, ``Future.result()``, ``run_coroutine_threadsafe(...).result()``, ...) or
  in ``Thread.join()`` can only be released by someone else, usually a task on this loop: it does not hold
  time, or the task that would release it could never run. A ``ThreadPoolExecutor`` worker waiting for its
  next job does not hold time either. (Telling these apart reads the threads' Python frames: see
  :mod:`asyncdonkey.clock._asyncio_internals`.)
* **Autojump threshold.** Daemon threads (a Donkeycar part's ``update()`` loop, a camera reader) and file
  descriptors registered with the loop (sockets, pipes, ptys) may answer at any moment, or never: they do not
  hold time, but while any is present the loop waits ``autojump_threshold`` of real time for them before each
  jump, so an answer already on its way arrives before time moves. With none present (the pure-virtual case)
  time jumps at once: 10,000 ticks of a 10-part car take about 0.07 s (`benchmarks/virtual_clock.py`).
* **Failures are named, once.** Nothing ready, no timer and nothing holding time means the program can never
  finish: :class:`VirtualClockDeadlock` lists the waiting tasks and the blocked threads, after waiting
  ``deadlock_grace_s`` of real time for outside I/O. A jump past ``budget_s`` of virtual time raises
  :class:`VirtualClockBudgetExceeded` naming the waiting tasks, instead of running away for hours of
  virtual time. Tasks that only ever yield (``while True: await asyncio.sleep(0)``) freeze virtual time:
  after ``livelock_s`` of real time (or ``livelock_iterations`` loop iterations) with no time moving and no
  outside work, :class:`VirtualClockLivelock` names them. After a first error the loop stops holding time
  for threads, so closing it neither waits again nor raises a second error that would hide the first.
* **Order.** Timers with equal deadlines fire in the order they were scheduled (a FIFO sequence number breaks
  ties), so two runs of the same program interleave identically.
* **Teardown.** ``shutdown_default_executor`` (called by ``asyncio.run``/``Runner`` with a 300 s timeout on
  Python 3.12+) holds time, so closing the loop neither jumps 300 s nor warns.

Threads and executors started *before* the loop was created are not watched (they cannot be working for it).
uvloop keeps its clock and timers inside libuv and cannot be virtualised: :func:`virtual_loop_factory`
refuses it loudly. Production runs on uvloop, tests and replays on this loop, and the runtime reads time from
whichever loop it is on (:func:`asyncdonkey.clock.get_clock`, through ``loop.is_virtual_clock``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextvars
import functools
import itertools
import math
import queue
import selectors
import sys
import threading
import time
import weakref
from asyncio import futures
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar, TypeVarTuple, Unpack

from ..errors import AsyncdonkeyError
from . import _asyncio_internals as _internals

_T = TypeVar("_T")
_Ts = TypeVarTuple("_Ts")

__all__ = [
    "VirtualClockBudgetExceeded",
    "VirtualClockDeadlock",
    "VirtualClockError",
    "VirtualClockLivelock",
    "VirtualClockLoop",
    "VirtualClockStall",
    "virtual_loop_factory",
]


class VirtualClockError(AsyncdonkeyError, RuntimeError):
    """Base class for virtual-clock failures."""


class VirtualClockDeadlock(VirtualClockError):
    """No task can ever run again: nothing ready, no timers, nothing holding time, no outside I/O."""


class VirtualClockStall(VirtualClockError):
    """Real work (executor calls, threads, subprocesses, holds) kept virtual time frozen for longer than
    ``stall_timeout_s`` of real time."""


class VirtualClockBudgetExceeded(VirtualClockError):
    """Virtual time would pass the loop's ``budget_s``: the program is waiting for something that does not come
    while timers keep firing."""


class VirtualClockLivelock(VirtualClockError):
    """Tasks kept the loop busy without letting virtual time move and without any outside work."""


_POLL_EVERY = 64  # without outside descriptors or working threads, real I/O is polled once in this many iterations
_LIVELOCK_CHECK_EVERY = 4096  # iterations between livelock checks (a power of two)
_RESCAN_EVERY = 64  # idle iterations between full thread censuses while the cached one says "quiet"


#: modules whose frames say nothing about what a thread is doing (the caller of their wait does)
_LIBRARY_FILES = frozenset(m.__file__ for m in (threading, concurrent.futures.thread, concurrent.futures._base, queue))


class _Job:
    """Executor work the loop is waiting for, and (for ``run_in_executor``) the thread running it: ``thread[0]``
    is that thread's ident while the function runs, ``None`` before and after."""

    __slots__ = ("name", "thread")

    def __init__(self, name: str) -> None:
        self.name = name
        self.thread: list[int | None] | None = None


class _Census:
    """What the threads started since the loop was created are doing, as far as the clock is concerned."""

    __slots__ = ("blocked", "holding", "live")

    def __init__(self) -> None:
        self.holding: list[str] = []  # working non-daemon threads and executor workers: time waits for them
        self.live: list[str] = []  # working daemon threads: time waits autojump_threshold for them
        self.blocked: list[str] = []  # waiting, without timeout, for someone else to release them


_QUIET = _Census()
_NO_EVENTS: tuple[()] = ()  # what a poll that found nothing returns (no list made per iteration)

# read on every tick: bound once
_Future = futures.Future
_getframe = sys._getframe
_thread_count = _internals.thread_count
_newest_thread = _internals.newest_thread
_WRAP_FUTURE = _internals.WRAP_FUTURE


_Events = Any  # what a selector's select() returns: a list of (SelectorKey, events) pairs, or _NO_EVENTS


class _VirtualSelector(selectors.DefaultSelector):
    """The platform selector, counting its registered file descriptors (one is the loop's wake-up pipe). The
    loop's own iteration polls it only when its policy says so; in debug mode asyncio's iteration runs instead,
    and the loop replaces this selector's ``select`` with the same policy."""

    #: the loop's policy, which asyncio's own iteration (debug mode) selects through: an instance attribute that
    #: stands in for the method (set by the loop; until then the platform's ``select``). The stub's type says a
    #: list; the policy returns an empty tuple when nothing is ready (no list made per iteration), which asyncio's
    #: iteration only loops over.
    select: Callable[[float | None], _Events]  # type: ignore[assignment]

    def __init__(self) -> None:
        super().__init__()
        self.n_fds = 0

    def register(self, fileobj: Any, events: int, data: Any = None) -> selectors.SelectorKey:
        key = super().register(fileobj, events, data)
        self.n_fds += 1
        return key

    def unregister(self, fileobj: Any) -> selectors.SelectorKey:
        key = super().unregister(fileobj)
        self.n_fds -= 1
        return key


if TYPE_CHECKING:

    class _SelectorEventLoop(asyncio.SelectorEventLoop):
        """asyncio's private loop members this loop uses, which typeshed's stubs leave out (types only: at run
        time the base is asyncio's own class, the else branch)."""

        _debug: bool

        def _check_closed(self) -> None: ...

        def _check_thread(self) -> None: ...

        def _check_callback(self, callback: object, method: str) -> None: ...

        async def _make_subprocess_transport(
            self, protocol: asyncio.BaseProtocol, args: Any, *rest: Any, **kwargs: Any
        ) -> asyncio.SubprocessTransport: ...
else:
    _SelectorEventLoop = asyncio.SelectorEventLoop


class VirtualClockLoop(_internals.LoopIteration, _SelectorEventLoop):
    """A selector event loop whose :meth:`time` is virtual and jumps to the next timer when all tasks wait.

    Use it as ``asyncio.Runner(loop_factory=VirtualClockLoop)`` or, in pytest, with ``@pytest.mark.asyncio``
    plus ``@pytest.mark.virtual_clock(**these_arguments)``.

    Args:
        start: the virtual time the loop starts at (seconds).
        autojump_threshold: real seconds (default 1 ms) the loop waits before a jump while a daemon thread at
            work or an outside file descriptor is present, so that an answer on its way arrives first. Without
            either, time jumps at once. ``0`` always jumps at once; a larger value lets slower peers keep up.
        budget_s: virtual seconds the loop may run (from ``start``); a jump beyond raises
            :class:`VirtualClockBudgetExceeded`. ``None``: no limit.
        deadlock_grace_s: real seconds (default 1) to wait for outside I/O before declaring a deadlock.
        stall_timeout_s: real seconds (default 60) real work may hold virtual time before
            :class:`VirtualClockStall`.
        livelock_s: real seconds (default 5) of busy iterations without time moving and without outside work before
            :class:`VirtualClockLivelock`. ``None``: never.
        livelock_iterations: the same limit counted in loop iterations (checked every 4,096). ``None``: none.
    """

    #: read by :func:`asyncdonkey.clock.get_clock` to take time from the loop itself
    is_virtual_clock = True
    #: asyncio's (private) selector: the one this loop made
    _selector: _VirtualSelector

    def __init__(
        self,
        *,
        start: float = 0.0,
        autojump_threshold: float = 0.001,
        budget_s: float | None = None,
        deadlock_grace_s: float = 1.0,
        stall_timeout_s: float = 60.0,
        livelock_s: float | None = 5.0,
        livelock_iterations: int | None = None,
    ) -> None:
        selector = _VirtualSelector()
        super().__init__(selector)
        broken = _internals_problems()
        if broken:
            self.close()
            raise VirtualClockError(
                f"VirtualClockLoop cannot run on Python {sys.version.split()[0]}: asyncio or threading changed in "
                f"ways it relies on: {'; '.join(broken)}"
            )
        if not autojump_threshold >= 0 or (budget_s is not None and not budget_s > 0):
            self.close()
            _check_budget(budget_s)
            raise ValueError(f"autojump_threshold must be >= 0 real seconds, got {autojump_threshold!r}")
        self._virtual_time = float(start)
        self._start = float(start)
        self._budget_end = math.inf
        self.budget_s = budget_s
        self.autojump_threshold = float(autojump_threshold)
        self.deadlock_grace_s = deadlock_grace_s
        self.stall_timeout_s = stall_timeout_s
        self.livelock_s = livelock_s
        self.livelock_iterations = livelock_iterations
        #: how many times virtual time jumped forward (a measure of how many "sleeps" the run had)
        self.jumps = 0
        self._timer_seq = itertools.count()
        self._jobs: dict[asyncio.Future[Any], _Job] = {}
        self._external_pending = 0
        self._holds: dict[int, tuple[str, Callable[[], bool]]] = {}
        self._hold_ids = itertools.count()
        self._procs: list[tuple[asyncio.SubprocessTransport, str]] = []
        self._threads_before: weakref.WeakSet[threading.Thread] = weakref.WeakSet(threading.enumerate())
        # The thread count and the newest thread when the last census found nothing to watch (a census is cached
        # while both stay the same: a thread started since changes the newest even if another one ended). At
        # first every thread is one from before the loop, so a loop that has not idled yet need not poll.
        self._quiet_threads = _thread_count()
        self._quiet_newest = _newest_thread()
        self._rescan = 0
        self._own_fds = selector.n_fds  # the wake-up pipe
        self._busy = 0
        self._spin_since: float | None = None
        self._failure: VirtualClockError | None = None
        self._idle = 0
        # the platform's select (the class's method: not yet replaced below)
        self._real_select: Callable[[float | None], list[tuple[selectors.SelectorKey, int]]] = selector.select
        selector.select = self._select  # asyncio's own iteration (debug mode) selects through the policy

    # -- time ---------------------------------------------------------------------------------------------
    def time(self) -> float:
        return self._virtual_time

    @property
    def budget_s(self) -> float | None:
        """Virtual seconds this loop may run from its start (``None``: no limit); may be changed at any time."""
        return None if self._budget_end == math.inf else self._budget_end - self._start

    @budget_s.setter
    def budget_s(self, value: float | None) -> None:
        _check_budget(value)
        self._budget_end = math.inf if value is None else self._start + float(value)

    def jump(self, seconds: float) -> None:
        """Move virtual time forward by ``seconds`` now (from the loop's thread). Timers that fall due fire on
        the next loop iteration, in deadline order; use it to skip a stretch in which nothing should happen."""
        if not seconds >= 0:
            raise ValueError(f"jump() moves time forward: seconds must be >= 0, got {seconds!r}")
        target = self._virtual_time + seconds
        if target > self._budget_end:
            raise self._fail(VirtualClockBudgetExceeded(self._budget_message(target, "jump()")))
        self._virtual_time = target
        self.jumps += 1

    def call_at(
        self,
        when: float,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        if when is None:
            raise TypeError("when cannot be None")
        if not self._debug:
            return _internals.schedule_timer(self, next(self._timer_seq), when, callback, args, context)
        self._check_closed()
        self._check_thread()
        self._check_callback(callback, "call_at")
        timer = _internals.SeqTimerHandle(next(self._timer_seq), when, callback, args, self, context)
        _internals.push_timer(self, timer)
        return timer

    def call_soon(
        self, callback: Callable[[Unpack[_Ts]], object], *args: *_Ts, context: contextvars.Context | None = None
    ) -> asyncio.Handle:
        if self._debug:
            return super().call_soon(callback, *args, context=context)
        return _internals.queue_callback(self, callback, args, context)

    def call_later(
        self,
        delay: float,
        callback: Callable[[Unpack[_Ts]], object],
        *args: *_Ts,
        context: contextvars.Context | None = None,
    ) -> asyncio.TimerHandle:
        if delay is None or self._debug:
            return super().call_later(delay, callback, *args, context=context)
        return self.call_at(self._virtual_time + delay, callback, *args, context=context)

    # -- executor tracking ---------------------------------------------------------------------------------
    def create_future(self) -> asyncio.Future[Any]:
        fut: asyncio.Future[Any] = _Future(loop=self)
        # called from asyncio.wrap_future: executor work is on its way (see _internals.WRAP_FUTURE)
        if _getframe(1).f_code is _WRAP_FUTURE:
            self._jobs[fut] = _Job("a concurrent.futures job")
            self._quiet_threads = -1
            fut.add_done_callback(self._job_done)
        return fut

    def run_in_executor(
        self, executor: concurrent.futures.Executor | None, func: Callable[[Unpack[_Ts]], _T], *args: *_Ts
    ) -> asyncio.Future[_T]:
        thread: list[int | None] = [None]

        def in_the_executor(*call_args: *_Ts) -> _T:
            thread[0] = threading.get_ident()
            try:
                return func(*call_args)
            finally:
                thread[0] = None

        fut = super().run_in_executor(executor, in_the_executor, *args)
        job = self._jobs.get(fut)
        if job is not None:
            job.name = _callable_name(func)
            job.thread = thread
        return fut

    def _job_done(self, fut: asyncio.Future[Any]) -> None:
        # a job cancelled while its thread still runs no longer holds time (nobody waits for it); if the
        # default executor's shutdown then waits for it, the stall message names it from the thread's frames
        self._jobs.pop(fut, None)

    async def shutdown_default_executor(self, *args: Any, **kwargs: Any) -> None:
        if self._failure is not None:
            # An error was raised already: its threads may never finish, and waiting for them would only
            # replace that error with a second one. Let them go, as a timed-out shutdown would.
            executor = getattr(self, "_default_executor", None)
            if executor is not None:
                executor.shutdown(wait=False)
            return
        self._external_pending += 1
        try:
            await super().shutdown_default_executor(*args, **kwargs)
        finally:
            self._external_pending -= 1

    async def _make_subprocess_transport(
        self, protocol: asyncio.BaseProtocol, args: Any, *rest: Any, **kwargs: Any
    ) -> asyncio.SubprocessTransport:
        transport = await super()._make_subprocess_transport(protocol, args, *rest, **kwargs)
        argv = [args] if isinstance(args, (str, bytes)) else list(args)
        self._procs.append((transport, f"subprocess {transport.get_pid()} ({' '.join(map(str, argv))[:60]})"))
        return transport

    def hold_time_while(self, busy: Callable[[], bool], name: str) -> Callable[[], None]:
        """Keep virtual time still while ``busy()`` returns true; returns a function that removes the hold.

        For a part whose own worker thread does real work on the loop's behalf (the tub writer's disk
        thread): like executor work, that work then takes no virtual time, so a simulated drive recorded on
        the virtual clock loses no records to a disk that is "infinitely slow" in virtual time. ``busy`` is
        called from the loop thread before each time jump and while waiting, so it must be cheap and
        thread-safe (reading counters is). While held, the loop polls ``busy`` every 2 ms of real time or sooner.
        """
        key = next(self._hold_ids)
        self._holds[key] = (name, busy)
        return lambda: self._holds.pop(key, None) and None

    # -- what holds time, what may answer ------------------------------------------------------------------
    def _census(self, force: bool = False) -> _Census:
        """Classify the threads started since this loop was created (cached while none needs watching)."""
        count = _thread_count()
        newest = _newest_thread()
        if not force and count == self._quiet_threads and newest is self._quiet_newest:
            self._rescan += 1
            if self._rescan < _RESCAN_EVERY:
                return _QUIET
        self._rescan = 0
        me = threading.get_ident()
        census = _Census()
        jobs = {job.thread[0]: job.name for job in self._jobs.values() if job.thread and job.thread[0] is not None}
        frames = sys._current_frames()
        try:  # frames are dropped before returning: see _thread_states
            for thread in threading.enumerate():
                ident = thread.ident
                if ident == me or thread in self._threads_before:
                    continue
                frame = frames.get(ident) if ident is not None else None
                if frame is not None and _internals.idle_pool_worker(frame):
                    continue
                wait = _internals.waiting(frame) if frame is not None else None
                name = _thread_name(thread, jobs.get(ident) if ident is not None else None, frame)
                if wait == "blocked":
                    census.blocked.append(name)
                elif not thread.daemon or ident in jobs:
                    census.holding.append(name)  # working, or in a timed wait (a threading.Timer)
                elif wait is None:
                    census.live.append(name)  # a daemon thread at work may answer the loop soon
                else:
                    census.blocked.append(name)  # a daemon thread waiting for work (a tub writer between records)
        finally:
            frame = None
            frames.clear()
        if not (census.holding or census.live or census.blocked):
            self._quiet_threads = count
            self._quiet_newest = newest
            return _QUIET
        self._quiet_threads = -1
        return census

    def _holders(self, census: _Census) -> list[str]:
        """Everything that holds virtual time still right now, by name."""
        if self._failure is not None:
            return []
        held = list(census.holding)
        if self._jobs:
            # A job holds time until its asyncio future is done (its result may be on its way to the loop
            # even after the thread finished), unless its thread is blocked waiting to be released.
            states = _thread_states()
            for job in self._jobs.values():
                ident = job.thread[0] if job.thread else None
                state = states.get(ident, _NO_FRAME) if ident is not None else _NO_FRAME
                if state is _NO_FRAME:
                    held.append(f"{job.name} (queued, finishing, or in a thread the loop cannot see)")
                elif state != "blocked" and not census.holding:
                    held.append(job.name)
        if self._procs:
            self._procs = [(p, name) for p, name in self._procs if p.get_returncode() is None]
            held += [name for _p, name in self._procs]
        if self._holds:
            held += [name for name, busy in list(self._holds.values()) if busy()]
        if self._external_pending:
            held.append("the default executor's shutdown")
        return held

    # -- the jump ------------------------------------------------------------------------------------------
    def _select(self, timeout: float | None) -> Any:
        """The selector's ``select`` in debug mode, where asyncio's own iteration runs: the same policy."""
        return self._poll_busy() if timeout == 0 else self._poll_idle(_internals.next_live_timer(self))

    def _poll_busy(self) -> Any:
        """Callbacks are ready (a busy iteration): time does not move; real I/O is polled now and then."""
        n = self._busy = self._busy + 1
        # Without threads at work, real I/O can wait a few iterations. With them, poll every time: the system
        # call releases the GIL, which a thread needs (a loop spinning on sleep(0) while an executor opens a
        # port would otherwise hand it over only every switch interval, 5 ms). Time does not move here, so the
        # thread count alone tells (a thread started as another ended is found by the next idle census).
        if n % _POLL_EVERY and not self._jobs and _thread_count() == self._quiet_threads:
            return _NO_EVENTS
        events_ = self._real_select(0)
        if events_:
            self._busy = 0
            self._spin_since = None
        elif not n % _LIVELOCK_CHECK_EVERY:
            self._check_livelock(n)
        return events_

    def _poll_idle(self, when: float | None) -> Any:
        """Every task waits (``when``: the earliest live timer's deadline, ``None`` without timers): poll outside
        I/O, wait while real work holds time, then jump to ``when``.

        This runs once per jump, so the common case (no thread, descriptor, job or hold to watch) reads a few
        counters and nothing else; the census of threads is cached while it finds none to watch.
        """
        self._busy = 0
        self._spin_since = None
        idle = self._idle = self._idle + 1
        # Poll real I/O before moving time. With no outside descriptor only the wake-up pipe could be ready, and
        # what matters on it (a thread's callback) is already in the ready queue: a signal handler added with
        # loop.add_signal_handler can wait a few jumps, as it waits a few busy iterations (_POLL_EVERY).
        outside = self._selector.n_fds > self._own_fds
        if outside or not idle % _POLL_EVERY:
            events_ = self._real_select(0)
            if events_:
                return events_
        if (
            self._rescan < _RESCAN_EVERY - 1
            and _thread_count() == self._quiet_threads
            and _newest_thread() is self._quiet_newest
        ):
            self._rescan += 1  # the cached census still holds: no thread to watch (_census, inlined)
            census = _QUIET
        else:
            census = self._census()
        # Real time passes here only while something is watched (threads, descriptors, jobs, holds); then a
        # thread's call_soon_threadsafe may arrive meanwhile, and must run before time moves. With nothing
        # watched, the ready queue was empty a moment ago (in _run_once) and is not looked at again.
        watched = outside
        if census is not _QUIET or self._jobs or self._procs or self._holds or self._external_pending:
            held = self._holders(census)
            if held:
                return self._wait_while_held(held)
            outside = outside or bool(census.live)
            when = _internals.next_live_timer(self)  # the holds' busy() ran: read the heap again
            watched = True
        if when is None:
            return self._nothing_scheduled(census)
        if outside and self.autojump_threshold > 0:
            events_ = self._real_select(self.autojump_threshold)
            if events_:
                return events_
        if watched and _internals.has_ready(self):
            return _NO_EVENTS
        if when > self._virtual_time:
            if when > self._budget_end:
                raise self._fail(VirtualClockBudgetExceeded(self._budget_message(when, "the next timer")))
            self._virtual_time = when
            self.jumps += 1
        return _NO_EVENTS

    def _wait_while_held(self, held: list[str]) -> list[Any]:
        """Wait in real time while real work holds virtual time; stall after ``stall_timeout_s``."""
        started = time.monotonic()
        pause = 0.0005
        while True:
            events_ = self._real_select(pause)  # executor results and threads' call_soon_threadsafe wake us at once
            if events_ or _internals.has_ready(self):
                return events_
            held = self._holders(self._census(force=True))
            if not held:
                return []
            if time.monotonic() - started > self.stall_timeout_s:
                raise self._fail(VirtualClockStall(self._stall_message(held)))
            pause = min(pause * 2, 0.002)  # a thread or a hold may end without waking the loop: poll

    def _nothing_scheduled(self, census: _Census) -> list[Any]:
        """No timer and nothing holding time: only outside I/O can still wake the loop."""
        deadline = time.monotonic() + self.deadlock_grace_s
        while True:
            events_ = self._real_select(min(0.02, max(0.0, deadline - time.monotonic())))
            if events_ or _internals.has_ready(self):
                return events_
            census = self._census(force=True)
            if self._holders(census):
                return []  # a thread went back to work: wait for it as usual
            if time.monotonic() >= deadline:
                raise self._fail(VirtualClockDeadlock(self._deadlock_message(census)))

    def _check_livelock(self, iterations: int) -> None:
        now = time.monotonic()
        if self._spin_since is None:
            self._spin_since = now
            return
        spun = now - self._spin_since
        too_long = self.livelock_s is not None and spun >= self.livelock_s
        too_many = self.livelock_iterations is not None and iterations >= self.livelock_iterations
        if not (too_long or too_many):
            return
        census = self._census(force=True)
        if self._holders(census) or census.live:
            self._spin_since = now  # a task polling for outside work is not a livelock
            return
        tasks = "; ".join(_describe_task(t) for t in _internals.ready_tasks(self)) or "none found"
        raise self._fail(
            VirtualClockLivelock(
                f"livelock at virtual time {self._virtual_time:.6f} s: for {iterations:,} loop iterations "
                f"({spun + 0.0:.1f} s of real time) tasks kept the loop busy without letting virtual time move, "
                f"while no thread, subprocess or file descriptor was working. A task that only ever yields "
                f"(while True: await asyncio.sleep(0)) freezes virtual time forever; await an event or a real "
                f"delay instead. Busy tasks: {tasks}"
            )
        )

    # -- errors --------------------------------------------------------------------------------------------
    def _fail(self, error: VirtualClockError) -> VirtualClockError:
        """Record the loop's first error; a later one says it came after it (and is usually its echo)."""
        if self._failure is None:
            self._failure = error
        elif error is not self._failure:
            error.args = (f"{error.args[0]} (after an earlier {type(self._failure).__name__}: {self._failure})",)
        return error

    def _waiting_tasks(self) -> str:
        waiting = [_describe_task(task) for task in asyncio.all_tasks(self) if not task.done()]
        return "; ".join(waiting) if waiting else "none"

    def _deadlock_message(self, census: _Census) -> str:
        outside = []
        if census.blocked:
            outside.append(f"threads blocked waiting to be released: {', '.join(census.blocked)}")
        if census.live:
            outside.append(f"daemon threads that did not call the loop: {', '.join(census.live)}")
        n_fds = self._selector.n_fds - self._own_fds
        if n_fds:
            outside.append(f"{n_fds} file descriptor(s) registered with the loop stayed silent")
        return (
            f"deadlock at virtual time {self._virtual_time:.6f} s: no callback is ready, no timer is scheduled, "
            f"nothing holds time (executor work, threads, subprocesses) and no I/O arrived within "
            f"{self.deadlock_grace_s:g} s of real time, so nothing can ever run again. "
            f"Waiting tasks: {self._waiting_tasks()}" + "".join(f". Also {o}" for o in outside)
        )

    def _stall_message(self, held: list[str]) -> str:
        if held == ["the default executor's shutdown"]:
            busy = self._census(force=True)
            if busy.holding or busy.blocked:
                held = [f"the default executor's shutdown, waiting for {', '.join(busy.holding + busy.blocked)}"]
        return (
            f"virtual time is frozen at {self._virtual_time:.6f} s: real work has not finished after "
            f"{self.stall_timeout_s:g} s of real time: {', '.join(held)}. Time stands still while executor "
            f"calls, non-daemon threads, subprocesses and hold_time_while() holds are busy; a loop that never "
            f"returns (for example a Donkeycar update()) must run in a daemon thread, and a thread that polls "
            f"with time.sleep() for something a task does looks busy (wait on an Event instead). "
            f"Waiting tasks: {self._waiting_tasks()}"
        )

    def _budget_message(self, when: float, what: str) -> str:
        return (
            f"virtual time budget exhausted: {what} would take virtual time to {when:.6f} s, past the budget of "
            f"{self.budget_s:g} s (from {self._start:g} s) after {self.jumps:,} jumps. The program is probably "
            f"waiting for something that never comes while timers keep firing; raise budget_s if it really "
            f"needs that long. Waiting tasks: {self._waiting_tasks()}"
        )


def _check_budget(value: float | None) -> None:
    if value is not None and not value > 0:
        raise ValueError(f"budget_s must be a positive number of virtual seconds or None, got {value!r}")


@functools.lru_cache(maxsize=1)
def _internals_problems() -> tuple[str, ...]:
    return tuple(_internals.problems())


def _callable_name(func: Any) -> str:
    """``Event.wait`` for a bound method, the wrapped function for ``asyncio.to_thread``'s partial."""
    while isinstance(func, functools.partial):
        runs_in_context = getattr(func.func, "__qualname__", "") == "Context.run" and func.args
        func = func.args[0] if runs_in_context else func.func
    return getattr(func, "__qualname__", None) or repr(func)


_NO_FRAME = object()


def _thread_states() -> dict[int, str | None]:
    """How each thread waits (:func:`_internals.waiting`), read from its innermost frame and nothing kept.

    Holding another thread's frame object while that frame returns makes CPython copy its local variables
    into the frame object (3.11+), keeping them alive as long as the frame object lives: a TFLite interpreter
    then refuses to run because a view of its buffer is still referenced. So frames are read in one pass here
    and dropped before returning.
    """
    frames = sys._current_frames()
    try:
        return {ident: _internals.waiting(frame) for ident, frame in frames.items()}
    finally:
        frames.clear()
        del frames


def _thread_name(thread: threading.Thread, job: str | None, frame: Any) -> str:
    what = f"running {job}" if job is not None else ""
    while frame is not None and frame.f_code.co_filename in _LIBRARY_FILES:
        frame = frame.f_back  # name the caller of Event.wait(), not threading.py
    where = f"at {frame.f_code.co_filename}:{frame.f_lineno}" if frame is not None else ""
    detail = ", ".join(x for x in (what, where) if x)
    return f"thread {thread.name!r}" + (f" ({detail})" if detail else "")


def _describe_task(task: asyncio.Task[Any]) -> str:
    """``name (coroutine at file:line, awaiting Event.wait)``: where the task's own code is suspended (the
    innermost frame outside asyncio) and, if different, the innermost coroutine it waits in."""
    coro: Any = task.get_coro()
    name = getattr(coro, "__qualname__", repr(coro))
    frame = getattr(coro, "cr_frame", None)
    innermost = coro
    inner = getattr(coro, "cr_await", None)
    while inner is not None and getattr(inner, "cr_frame", None) is not None:
        innermost = inner
        if not inner.cr_frame.f_code.co_filename.startswith(_ASYNCIO_DIR):
            frame = inner.cr_frame
        inner = getattr(inner, "cr_await", None)
    where = f" at {frame.f_code.co_filename}:{frame.f_lineno}" if frame is not None else ""
    if innermost is not coro and frame is not getattr(innermost, "cr_frame", None):
        where += f", awaiting {getattr(innermost, '__qualname__', innermost)}"
    return f"{task.get_name()} ({name}{where})"


_ASYNCIO_DIR = asyncio.__file__.rsplit("__init__", 1)[0]


def virtual_loop_factory(backend: str = "asyncio", **kwargs: Any) -> Callable[[], VirtualClockLoop]:
    """A loop factory for ``asyncio.Runner``. Only the asyncio selector loop can run on virtual time."""
    if backend != "asyncio":
        raise VirtualClockError(
            f"a virtual clock is not available for the {backend!r} event loop: uvloop keeps its clock and "
            f"timers inside libuv, where they cannot be replaced. Run tests on VirtualClockLoop (the asyncio "
            f"selector loop) and production on uvloop; the runtime takes its clock from whichever it runs on."
        )
    return lambda: VirtualClockLoop(**kwargs)
