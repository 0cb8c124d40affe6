"""An asyncio event loop on virtual time: hours of driving in a second, the same result every run.

Semantics follow Trio's ``MockClock`` with autojump (DESIGN.md §4): time moves only when nothing is runnable,
and then straight to the next timer's deadline, exactly, never backwards. A part that awaits
``asyncio.sleep(0.08)`` costs exactly 80 ms of loop time.

How it works, and why this way:

* The loop is a plain :class:`asyncio.SelectorEventLoop` whose :meth:`time` returns a stored float. asyncio
  only blocks in ``selector.select(timeout)`` when its ready queue is empty, so "every task is blocked" is
  exactly "select was called with a timeout > 0". Our selector first polls real I/O with a zero timeout
  (a pty, a pipe, or a thread's ``call_soon_threadsafe`` wake-up may be waiting); if nothing is there it
  sets virtual time to the earliest live timer's deadline in a single step. Tools that patch the selector
  instead (looptime) spend dozens of no-op loop cycles per jump.
* **Executors.** Futures from ``run_in_executor`` (and so ``asyncio.to_thread``) are tracked. While any is
  pending, the selector waits in *real* time and virtual time stands still: a thread doing 50 ms of real work
  costs 0 virtual time, and a 1 s sleeper beside it still wakes at exactly +1 s. A pending call that makes no
  progress for ``stall_timeout_s`` of real time raises :class:`VirtualClockStall` naming it (a long-lived
  blocking loop such as a Donkeycar ``update()`` must run in its own thread, not in the executor).
  A part with a worker thread of its own (the tub writer) registers ``hold_time_while(busy)``: while
  ``busy()`` is true, time stands still in the same way, so its work also costs 0 virtual time.
* **Deadlock.** Nothing ready, no timer, no executor work and no I/O within ``deadlock_grace_s`` of real time
  means the program can never finish: :class:`VirtualClockDeadlock` is raised with the waiting tasks listed,
  instead of hanging the test run.
* **Order.** Timers with equal deadlines fire in the order they were scheduled (a FIFO sequence number breaks
  ties), so two runs of the same program interleave identically.
* **Teardown.** ``shutdown_default_executor`` (called by ``asyncio.run``/``Runner`` with a 300 s timeout on
  Python 3.12+) counts as pending real work, so closing the loop neither jumps 300 s nor warns.

uvloop keeps its clock and timers inside libuv and cannot be virtualised: :func:`virtual_loop_factory` refuses
it loudly. Production runs on uvloop, tests on this loop, and the runtime reads time from whichever loop it is
on (:func:`asyncdonkey.clock.get_clock`).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import selectors
import time
from asyncio import events
from collections.abc import Callable
from typing import Any

__all__ = [
    "VirtualClockDeadlock",
    "VirtualClockError",
    "VirtualClockLoop",
    "VirtualClockStall",
    "virtual_loop_factory",
]


class VirtualClockError(RuntimeError):
    """Base class for virtual-clock failures."""


class VirtualClockDeadlock(VirtualClockError):
    """No task can ever run again: nothing ready, no timers, no executor work, no I/O."""


class VirtualClockStall(VirtualClockError):
    """Executor work kept virtual time frozen for longer than ``stall_timeout_s`` of real time."""


class _SeqTimerHandle(events.TimerHandle):
    """A timer handle ordered by (deadline, scheduling sequence) so equal deadlines fire FIFO."""

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

    def __lt__(self, other: object) -> bool:
        if isinstance(other, _SeqTimerHandle):
            return (self._when, self._seq) < (other._when, other._seq)
        return super().__lt__(other)

    def __le__(self, other: object) -> bool:
        if isinstance(other, _SeqTimerHandle):
            return (self._when, self._seq) <= (other._when, other._seq)
        return super().__le__(other)


class _VirtualSelector(selectors.DefaultSelector):  # type: ignore[misc,valid-type]
    """The platform selector, with ``select`` routed through the loop's virtual-time policy."""

    def __init__(self) -> None:
        super().__init__()
        self.policy: Callable[[Callable[[float | None], list[Any]], float | None], list[Any]] | None = None

    def select(self, timeout: float | None = None) -> list[Any]:
        real = super().select
        if self.policy is None:
            return real(timeout)
        return self.policy(real, timeout)


class VirtualClockLoop(asyncio.SelectorEventLoop):
    """A selector event loop whose :meth:`time` is virtual and jumps to the next timer when all are blocked.

    Use it as ``asyncio.Runner(loop_factory=VirtualClockLoop)`` or, in pytest, with
    ``@pytest.mark.asyncio`` plus ``@pytest.mark.virtual_clock``.

    Args:
        start: the virtual time the loop starts at (seconds).
        deadlock_grace_s: real seconds to wait for outside I/O before declaring a deadlock.
        stall_timeout_s: real seconds pending executor work may hold virtual time before
            :class:`VirtualClockStall` is raised.
    """

    #: read by :func:`asyncdonkey.clock.get_clock` to take time from the loop itself
    is_virtual_clock = True

    def __init__(self, *, start: float = 0.0, deadlock_grace_s: float = 1.0, stall_timeout_s: float = 60.0) -> None:
        selector = _VirtualSelector()
        super().__init__(selector)
        self._virtual_time = float(start)
        self._timer_seq = itertools.count()
        self._pending_executor: dict[asyncio.Future[Any], str] = {}
        self._external_pending = 0
        self._holds: dict[int, tuple[str, Callable[[], bool]]] = {}
        self._hold_ids = itertools.count()
        self.deadlock_grace_s = deadlock_grace_s
        self.stall_timeout_s = stall_timeout_s
        #: how many times virtual time jumped forward (a measure of how many "sleeps" the run had)
        self.jumps = 0
        selector.policy = self._select

    # -- time ---------------------------------------------------------------------------------------------
    def time(self) -> float:
        return self._virtual_time

    def call_at(self, when: float, callback: Callable[..., Any], *args: Any, context: Any = None) -> Any:
        if when is None:
            raise TypeError("when cannot be None")
        self._check_closed()
        if self._debug:
            self._check_thread()
            self._check_callback(callback, "call_at")
        timer = _SeqTimerHandle(next(self._timer_seq), when, callback, args, self, context)
        if timer._source_traceback:
            del timer._source_traceback[-1]
        heapq.heappush(self._scheduled, timer)
        timer._scheduled = True
        return timer

    # -- executor tracking ---------------------------------------------------------------------------------
    def run_in_executor(self, executor: Any, func: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        fut = super().run_in_executor(executor, func, *args)
        self._pending_executor[fut] = getattr(func, "__qualname__", repr(func))
        fut.add_done_callback(self._executor_done)
        return fut

    def _executor_done(self, fut: asyncio.Future[Any]) -> None:
        self._pending_executor.pop(fut, None)

    async def shutdown_default_executor(self, *args: Any, **kwargs: Any) -> None:
        self._external_pending += 1
        try:
            await super().shutdown_default_executor(*args, **kwargs)
        finally:
            self._external_pending -= 1

    @property
    def pending_executor_calls(self) -> list[str]:
        """Names of the functions whose executor calls are still running (virtual time waits for them)."""
        return list(self._pending_executor.values())

    def hold_time_while(self, busy: Callable[[], bool], name: str) -> Callable[[], None]:
        """Keep virtual time still while ``busy()`` returns true; returns a function that removes the hold.

        For a part whose own worker thread does real work on the loop's behalf (the tub writer's disk
        thread): like executor work, that work then takes no virtual time, so a simulated drive recorded on
        the virtual clock loses no records to a disk that is "infinitely slow" in virtual time. ``busy`` is
        called from the loop thread before each time jump and while waiting, so it must be cheap and
        thread-safe (reading counters is). While held, the loop polls ``busy`` every millisecond of real time.
        """
        key = next(self._hold_ids)
        self._holds[key] = (name, busy)
        return lambda: self._holds.pop(key, None) and None

    def _held_by(self) -> list[str]:
        return [name for name, busy in list(self._holds.values()) if busy()]

    # -- the jump ------------------------------------------------------------------------------------------
    def _select(self, real_select: Callable[[float | None], list[Any]], timeout: float | None) -> list[Any]:
        events_ = real_select(0)
        if events_ or timeout == 0:
            return events_
        if self._pending_executor or self._external_pending or (self._holds and self._held_by()):
            return self._wait_for_real_work(real_select)
        scheduled = self._scheduled
        while scheduled and scheduled[0]._cancelled:
            self._timer_cancelled_count -= 1
            heapq.heappop(scheduled)._scheduled = False
        if scheduled:
            when = scheduled[0]._when
            if when > self._virtual_time:
                self._virtual_time = when
                self.jumps += 1
            return []
        # No timers and nothing pending: only outside I/O could still wake us.
        events_ = real_select(self.deadlock_grace_s)
        if events_:
            return events_
        raise VirtualClockDeadlock(self._deadlock_message())

    def _wait_for_real_work(self, real_select: Callable[[float | None], list[Any]]) -> list[Any]:
        started = time.monotonic()
        while True:
            held = self._held_by() if self._holds else []
            # executor futures wake the selector when done; holds are polled
            events_ = real_select(0.001 if held else 0.25)
            if events_:
                return events_
            if not (self._pending_executor or self._external_pending or (self._holds and self._held_by())):
                return events_
            if time.monotonic() - started > self.stall_timeout_s:
                calls = ", ".join(self.pending_executor_calls + self._held_by()) or "default executor shutdown"
                raise VirtualClockStall(
                    f"virtual time is frozen: executor work ({calls}) has not finished after "
                    f"{self.stall_timeout_s:.0f} s of real time. A blocking loop that never returns (for "
                    f"example a Donkeycar update()) must run in its own thread, not in run_in_executor."
                )

    def _deadlock_message(self) -> str:
        waiting = []
        for task in asyncio.all_tasks(self):
            if not task.done():
                coro = task.get_coro()
                frame = getattr(coro, "cr_frame", None)
                where = f" at {frame.f_code.co_filename}:{frame.f_lineno}" if frame is not None else ""
                waiting.append(f"{task.get_name()} ({getattr(coro, '__qualname__', coro)}{where})")
        listed = "; ".join(waiting) if waiting else "none"
        return (
            f"deadlock at virtual time {self._virtual_time:.6f} s: no callback is ready, no timer is "
            f"scheduled, no executor work is pending and no I/O arrived within {self.deadlock_grace_s:g} s of "
            f"real time, so nothing can ever run again. Waiting tasks: {listed}"
        )


def virtual_loop_factory(backend: str = "asyncio", **kwargs: Any) -> Callable[[], VirtualClockLoop]:
    """A loop factory for ``asyncio.Runner``. Only the asyncio selector loop can run on virtual time."""
    if backend != "asyncio":
        raise VirtualClockError(
            f"a virtual clock is not available for the {backend!r} event loop: uvloop keeps its clock and "
            f"timers inside libuv, where they cannot be replaced. Run tests on VirtualClockLoop (the asyncio "
            f"selector loop) and production on uvloop; the runtime takes its clock from whichever it runs on."
        )
    return lambda: VirtualClockLoop(**kwargs)
