"""Pipelined parts: heavy work beside the ticks instead of inside them.

Why. Run in order, a part that takes 80 ms (a pilot's inference on a Raspberry Pi 4) makes a 20 Hz tick take
89 ms: the loop falls to about 11 Hz and everything in it (the controller, recording, the failsafe) slows down
with it. Added with ``pipelined=True`` the part runs in a task of its own: whenever it is free it takes the
newest inputs, computes (a sync ``run`` in a worker thread), and publishes its outputs, which the ticks read as
latest values without waiting. It never queues: a start requested while it is busy is remembered once and served
with the inputs as they are when it is free.

When it starts:

* **at each tick** (default): in its place in the part order, so it sees what the parts before it wrote on that
  tick (the camera's frame);
* **on a new value** (``trigger="cam/image_array"``): the moment that input gets a value with a new origin. A
  source that pushes (a part with ``subscribe(callback)``, like the cameras) writes its value into Memory as
  soon as it exists, not at the next tick, so the pilot starts on the frame the moment it is captured.

Its outputs carry the origin of the inputs it read (not of the time it finished), so ``pilot/throttle@age`` is
the true age of the sensing behind the command, and the stale-command failsafe covers a pilot that dies or falls
behind. Parts added with ``react=True`` downstream of it (``DriveMode``, the actuators), or downstream of a push
source (a command received from the network), also run the moment it publishes, so a new command reaches the
output without waiting for the next tick.

**One call at a time.** A part is never entered while it is still running, whatever path calls it: the tick, a
pipelined part's worker, the reactions to a pipelined part or to a push source (a push itself calls no part: it
stores the source's value and starts the reactions). Only a part that yields while it runs can be caught inside
its call (an ``async run()``, or a sync one in a worker thread: ``executor=True`` or pipelined), so the drive
decides when it starts which entries need a :class:`ReentryGuard`: a ``react=True`` part that awaits and that a
pipelined part or a push source feeds (the tick and its reactions can both call it), and an executor part with a
``timeout`` (a call that times out leaves its thread running). The others, a sync part on the loop thread above
all, run as before: the tick does nothing more for them. A call that finds its part busy is never lost and never
queued behind old ones; newest wins:

* the first to find it busy **waits** for the running call to end, then runs it with the inputs as they are
  then (the tick included: so the tick keeps its order and its later parts see this part's outputs);
* any that arrive while one is already waiting are **coalesced** into it: that run reads inputs at least as new
  as theirs, and they wait for it to end (so their own later parts see its outputs too) without running again;
* a wait is bounded by the part's ``timeout`` when it has one (a thread left running by a timed-out call may
  never end): the waiting call then fails with :class:`~asyncdonkey.errors.PartTimeoutError`, as a call that
  did not return in time does.

Nothing waits for a call while holding another part, so the waits cannot deadlock. Each guarded part's
``waited`` and ``coalesced`` counts are in ``DriveReport.reentries_avoided``; a push that comes while the
reactions to the previous one still run is superseded by the next (counted in ``DriveReport.pushed``), as a
pipelined part's starts are (``DriveReport.pipelined``).

What each mode keeps and loses is in ``docs/control-periods.md``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import threading
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from ..errors import PartTimeoutError
from .partrun import CallGuard, PartRun
from .plan import with_timeout
from .runtypes import TickStep

if TYPE_CHECKING:
    from ..clock import Clock
    from ..memory import Memory

__all__ = ["GuardedTick", "Pipeline", "ReentryGuard", "TickKicker", "build_pipelines", "needs_guard"]

logger = logging.getLogger("asyncdonkey.loop")


class PipelineWork(Protocol):
    """What the pipelines use of the drive's background work: the wiring fills its push sources and re-entry
    guards, a guarded executor part's calls use its worker pool."""

    push_sources: list[tuple[PartRun, Any, Reaction | None]]
    reentry_guards: list[ReentryGuard]

    def get_executor(self) -> concurrent.futures.Executor: ...


class PipelineHost(Protocol):
    """What the pipelines and reactions use of the drive they run beside (``runs``: each part's
    :class:`~asyncdonkey.core.partrun.PartRun` for this drive, in add() order)."""

    @property
    def runs(self) -> Sequence[PartRun]: ...

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    @property
    def clock(self) -> Clock: ...

    @property
    def mem(self) -> Memory: ...

    @property
    def on(self) -> bool: ...

    #: the work beside the ticks (``asyncdonkey.core.drivestate.BackgroundWork``)
    @property
    def work(self) -> PipelineWork: ...

    def background_failed(self, e: PartRun, exc: BaseException, what: str = ...) -> None: ...


class Pipeline:
    """One pipelined part's worker task, its start requests and its counters."""

    def __init__(self, drive: PipelineHost, run: PartRun, react: list[PartRun]) -> None:
        self.drive = drive
        self.run = run
        self.entry = run.entry
        self.react = react
        self.name = run.name
        self.trigger = run.entry.beside.trigger
        self._kick = asyncio.Event()
        self.busy = False
        self.runs = 0
        self.published = 0
        self.superseded = 0
        self.first_start: float | None = None
        self.last_start = 0.0
        self._last_trigger_origin: float | None = None
        self.task: asyncio.Task[None] | None = None

    # -------------------------------------------------------------------------------------- starting
    def kick(self) -> None:
        if self._kick.is_set():
            self.superseded += 1  # a start still pending is replaced by this newer one: its inputs were skipped
        self._kick.set()

    def new_value(self, origin: float | None) -> None:
        """The trigger input was written: start if its origin is new (a new frame, not the same one again)."""
        if origin is not None and origin == self._last_trigger_origin:
            return
        self._last_trigger_origin = origin
        self.kick()

    # ----------------------------------------------------------------------------------------- worker
    async def main(self) -> None:
        drive = self.drive
        e = self.run
        d = drive.mem.d
        now = drive.clock.now
        series = e.series
        stated = getattr(e.entry.part, "output_origin", None)
        stated = stated if callable(stated) else None
        while True:
            await self._kick.wait()
            self._kick.clear()
            if not drive.on:
                return
            cond = e.run_condition
            if cond is not None and not d.get(cond):
                continue
            self.busy = True
            t = now()
            if self.first_start is None:
                self.first_start = t
            self.last_start = t
            self.runs += 1
            try:
                t_end, published = await self._run_once(t, stated)
                if published and self.react:
                    await self._react(t_end)
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                t_end = now()
                self._failed(e, exc)
            finally:
                self.busy = False
            series.record(t_end - t)

    async def _run_once(self, t: float, stated: Callable[[], float | None] | None) -> tuple[float, bool]:
        """One run on the newest inputs: ``(its end, whether it published)``. A guarded part (an executor part with
        a timeout) is entered through its guard first: a thread its last call's timeout left running keeps it."""
        e = self.run
        guard = e.reentry_guard
        if guard is not None and not await guard.enter():
            return self.drive.clock.now(), False  # (only this worker calls it: never coalesced)
        try:
            args = e.args()
            origin = e.input_origin() if e.input_origin is not None else t
            r = e.call(*args) if guard is None else guard.call(*args)
            if e.awaits:
                r = await r
            t_end = self.drive.clock.now()
            if r is None or e.store_fixed is None:
                return t_end, False
            if stated is not None:
                o = stated()
                origin = origin if o is None else o
            e.store_fixed(r, origin, t_end)
            self.published += 1
            return t_end, True
        finally:
            if guard is not None:
                guard.leave()

    async def _react(self, t: float) -> None:
        await run_reactions(self.drive, self.react, self._failed)

    def _failed(self, e: PartRun, exc: Exception) -> None:
        self.drive.background_failed(e, exc, "pipelined run()" if e is self.run else "reacting run()")

    def stats(self, elapsed: float) -> dict[str, float]:
        span = self.last_start - self.first_start if self.first_start is not None else 0.0
        return {
            "runs": self.runs,
            "published": self.published,
            "rate_hz": (self.runs - 1) / span if self.runs > 1 and span > 0 else 0.0,
            "superseded": self.superseded,
        }


async def run_reactions(
    drive: PipelineHost, entries: list[PartRun], failed: Callable[[PartRun, Exception], None]
) -> None:
    """Run the ``react=True`` parts ``entries`` now, in their add() order (after a pipelined part or a push
    source published): a new command reaches the actuators without waiting for the next tick."""
    d = drive.mem.d
    now = drive.clock.now
    for e in entries:
        cond = e.run_condition
        if cond is not None and not d.get(cond):
            continue
        guard = e.reentry_guard
        try:
            if guard is not None:  # the tick or another reaction may be inside its call: one call at a time
                t_end = await guard.run_stored()
                if t_end is None:
                    continue  # coalesced: a run that started after this request has just ended
            else:
                args = e.args()
                r = e.call(*args)
                if e.awaits:
                    r = await r
                t_end = now()
                if r is not None and e.store is not None:
                    e.store(r, args, t_end)
            if e.latency is not None:
                e.latency(t_end)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            failed(e, exc)


class Reaction:
    """The ``react=True`` parts downstream of a push source, run in a task of their own each time it pushes
    (a start requested while they run is served once more, with the newest values, never queued)."""

    def __init__(self, drive: PipelineHost, entries: list[PartRun]) -> None:
        self.drive = drive
        self.entries = entries
        self._kick = asyncio.Event()
        self.runs = 0
        self.superseded = 0
        self.task: asyncio.Task[None] | None = None

    def kick(self) -> None:
        if self._kick.is_set():
            self.superseded += 1  # the push still waiting for its reactions is replaced by this newer one
        self._kick.set()

    def stats(self) -> dict[str, int]:
        return {"reactions": self.runs, "superseded": self.superseded}

    async def main(self) -> None:
        drive = self.drive
        while True:
            await self._kick.wait()
            self._kick.clear()
            if not drive.on:
                return
            self.runs += 1
            await run_reactions(drive, self.entries, lambda e, exc: drive.background_failed(e, exc, "reacting run()"))


def react_chain(runs: Sequence[PartRun], channels: set[str]) -> list[PartRun]:
    """The ``react=True`` parts fed, directly or through each other, by ``channels``, in add() order."""
    chain: list[PartRun] = []
    channels = set(channels)
    for r in runs:
        if r.entry.beside.react and channels.intersection(i for i in r.inputs if i is not None):
            chain.append(r)
            channels.update(r.outputs)
    return chain


class TickKicker(TickStep):
    """What the tick calls in a pipelined part's place: start it if it starts on ticks (the tick skips it when its
    run condition is false, from ``run_condition``, as any part). A :class:`~asyncdonkey.core.runtypes.TickStep`
    with nothing of its own: its call only kicks, so it never awaits, stores or fails."""

    __slots__ = ()

    def __init__(self, pipeline: Pipeline) -> None:
        e = pipeline.run
        self.name = e.name
        self.run_condition = e.run_condition
        self.args = _no_args
        self.call = pipeline.kick if pipeline.trigger is None else _nothing
        self.awaits = False
        self.is_sync_inline = False
        self.store = None
        self.kicks = ()
        self.latency = None
        self.on_error = "continue"
        self.errors = 0
        self.timeout = None


def _no_args() -> tuple[()]:
    return ()


def _nothing() -> None:
    return None


# ------------------------------------------------------------------------------------ one call at a time
def needs_guard(e: PartRun, reacting: set[int]) -> bool:
    """Whether two calls of ``e`` could be inside it at once (``reacting``: ids of the parts some reaction runs).

    Only a call that yields can be caught inside: an awaited one (``async run()``, or a sync one in a worker
    thread). So: an awaited part that reactions run besides the tick, and an executor part with a timeout, whose
    call, timed out, leaves its thread running while the next one comes. A sync part on the loop thread runs to its
    end before anything else can call it, and a pipelined part is only called by its own worker, one run after the
    other: neither needs one (unless its thread can outlive a timeout).
    """
    if e.awaits and id(e) in reacting:
        return True
    return e.entry.executor and e.timeout is not None


class ReentryGuard:
    """Keeps one part from being entered while it is still running, for every path that calls it.

    A path calls :meth:`enter` before reading the part's inputs and :meth:`leave` after storing its outputs, and
    calls it through :attr:`call` (an executor part's calls are offloaded here, so that the part stays busy until
    its thread has really ended, not only until its caller stopped waiting). What a path that finds it busy
    does (wait, or be coalesced into the one already waiting; newest wins) is in the module docstring.
    """

    __slots__ = (
        "_holds",
        "_idle",
        "_loop",
        "_next",
        "_now",
        "_origins",
        "_serving",
        "_timeout",
        "busy",
        "call",
        "coalesced",
        "name",
        "run",
        "waited",
    )

    def __init__(self, drive: PipelineHost, run: PartRun) -> None:
        self.run = run
        self.name = run.name
        self.busy = False
        #: calls that found it running and waited for that call to end, then ran it
        self.waited = 0
        #: calls that found it running with another already waiting, and were served by that one's run
        self.coalesced = 0
        #: what keeps it busy: the path inside it, and a worker thread still running its call
        self._holds = 0
        self._idle: asyncio.Future[None] | None = None  # done when it is let go: wakes the waiting call
        self._next: asyncio.Future[bool] | None = None  # the waiting call's: True once it has run, False if it gave up
        self._serving: asyncio.Future[bool] | None = None  # the running call's own, when it had waited
        self._loop = drive.loop
        self._now = drive.clock.now
        self._origins = drive.mem.origins
        self._timeout = run.timeout
        self.call: Callable[..., Awaitable[Any]] = self._thread_call(drive) if run.entry.executor else run.call

    # -------------------------------------------------------------------------------------- entering
    async def enter(self) -> bool:
        """Take the part. ``True``: this caller runs it now, then calls :meth:`leave`; ``False``: this request was
        coalesced into a waiting one, which has run the part since, on inputs at least as new as this one's."""
        if not self.busy and self._next is None:
            self.busy = True
            self._holds = 1
            return True
        return await self._when_busy()

    async def _when_busy(self) -> bool:
        """Wait for the running call and take the part, or, if a call already waits, be served by its run. A loop:
        the call this one was coalesced into may give up (cancelled at the drive's end) before it ran."""
        counted = False
        while True:
            nxt = self._next
            if nxt is None:
                if not self.busy:  # the call it was coalesced into gave up (cancelled), and the part is free
                    self.busy = True
                    self._holds = 1
                    return True
                self.waited += 1
                return await self._wait_then_take()
            if not counted:
                self.coalesced += 1
                counted = True
            if await asyncio.shield(nxt):
                return False

    async def _wait_then_take(self) -> bool:
        nxt = self._next = self._loop.create_future()
        try:
            if self._timeout is None:
                await self._until_free()
            else:
                try:
                    async with asyncio.timeout(self._timeout):
                        await self._until_free()
                except TimeoutError:
                    raise PartTimeoutError(
                        f"was still running a call that began before this one's {self._timeout:g} s timeout"
                    ) from None
        except BaseException:
            self._next = None
            if not nxt.done():
                nxt.set_result(False)  # the calls coalesced into this one try again
            raise
        self._next = None
        self._serving = nxt
        self.busy = True
        self._holds = 1
        return True

    async def _until_free(self) -> None:
        while self.busy:
            idle = self._idle
            if idle is None or idle.done():
                idle = self._idle = self._loop.create_future()
            await idle

    # --------------------------------------------------------------------------------------- leaving
    def leave(self) -> None:
        """The path is done with the part (its outputs stored): the calls coalesced into this one are served."""
        serving = self._serving
        if serving is not None:
            self._serving = None
            if not serving.done():
                serving.set_result(True)
        self._let_go()

    def _let_go(self) -> None:
        self._holds -= 1
        if self._holds:
            return
        self.busy = False
        idle = self._idle
        if idle is not None:
            self._idle = None
            if not idle.done():
                idle.set_result(None)

    # ------------------------------------------------------------------------------------------ calls
    async def run_stored(self, kicks: bool = False) -> float | None:
        """Enter, read the inputs as they are now, call, store the outputs (and with ``kicks``, start what they
        trigger, as the tick does); the end time, or ``None`` when coalesced into a run that has just ended."""
        if self.busy or self._next is not None:
            if not await self._when_busy():
                return None
        else:  # enter()'s free case, inlined: this runs on every tick of a guarded part
            self.busy = True
            self._holds = 1
        e = self.run
        try:
            args = e.args()
            r = await self.call(*args)
            t_end = self._now()
            if r is not None and e.store is not None:
                e.store(r, args, t_end)
                if kicks and e.kicks:
                    after_store(e, self._origins)
        finally:
            self.leave()
        return t_end

    def _thread_call(self, drive: PipelineHost) -> Callable[..., Awaitable[Any]]:
        """The part's call in a worker thread, which keeps the part busy until the thread is done with it.

        A caller that stops waiting (a timeout, a cancellation) does not stop the thread: the part is let go when
        the thread returns, or at once if the call had not started (it then never will).
        """
        fn, loop, executor = self.run.entry.fn, self._loop, drive.work.get_executor
        lock = threading.Lock()

        def claimed(state: list[str], args: tuple[Any, ...]) -> Any:
            with lock:
                if state[0] != "queued":
                    return None  # its caller gave up before it started
                state[0] = "running"
            try:
                return fn(*args)
            finally:
                self._thread_ended()

        claimed.__qualname__ = getattr(fn, "__qualname__", self.name)  # what the virtual clock names the job

        def offloaded(*args: Any) -> asyncio.Future[Any]:
            state = ["queued"]

            def given_up(fut: asyncio.Future[Any]) -> None:
                if fut.cancelled():
                    with lock:
                        if state[0] == "queued":
                            state[0] = "abandoned"
                            self._let_go()

            fut = loop.run_in_executor(executor(), claimed, state, args)
            self._holds += 1
            fut.add_done_callback(given_up)
            return fut

        return with_timeout(offloaded, self._timeout, self.name) if self._timeout is not None else offloaded

    def _thread_ended(self) -> None:
        try:
            self._loop.call_soon_threadsafe(self._let_go)
        except RuntimeError:  # the loop has closed: the drive is over
            pass

    def stats(self) -> dict[str, int]:
        return {"waited": self.waited, "coalesced": self.coalesced}


class GuardedTick(TickStep):
    """What the tick calls in a guarded part's place: one awaitable that enters the part (waiting for a call from
    another path to end), reads its inputs then, calls it and stores its outputs (so the tick stores nothing).

    A :class:`~asyncdonkey.core.runtypes.TickStep` whose ``errors`` and ``latency`` are its part's run's (the
    latency recorder is attached to the run once the drive has started)."""

    __slots__ = ("run",)

    def __init__(self, guard: CallGuard) -> None:
        e = self.run = guard.run
        self.name = e.name
        self.run_condition = e.run_condition
        self.on_error = e.on_error
        self.timeout = e.timeout
        self.args = _no_args
        self.call = functools.partial(guard.run_stored, True)  # with kicks, as the tick starts what its stores trigger
        self.awaits = True
        self.store = None
        self.kicks = ()
        self.is_sync_inline = False

    @property
    def latency(self) -> Callable[[float], None] | None:
        return self.run.latency

    @latency.setter
    def latency(self, recorder: Callable[[float], None] | None) -> None:
        self.run.latency = recorder

    @property
    def errors(self) -> int:
        return self.run.errors

    @errors.setter
    def errors(self, n: int) -> None:
        self.run.errors = n


def build_pipelines(drive: PipelineHost) -> tuple[tuple[TickStep, ...], list[Pipeline]]:
    """The tick's list (the drive's :class:`~asyncdonkey.core.partrun.PartRun` of each part, pipelined parts replaced by
    their kickers) and the drive's pipelines.

    Also wires the triggers: parts whose outputs feed a trigger get ``kicks`` (checked after their store), and
    push sources (parts with ``subscribe``) feeding a trigger or ``react=True`` parts are subscribed for the
    drive. All of it on the runs: the vehicle's entries (its plan) are only read.
    """
    entries = drive.runs
    pipelines: list[Pipeline] = []
    tick: list[TickStep] = []
    for e in entries:
        if not e.entry.beside.pipelined:
            tick.append(e)
            continue
        p = Pipeline(drive, e, react_chain(entries, set(e.outputs)))
        pipelines.append(p)
        tick.append(TickKicker(p))
    by_trigger: dict[str, list[Pipeline]] = {}
    for p in pipelines:
        if p.trigger is not None:
            by_trigger.setdefault(p.trigger, []).append(p)
    for e in entries:
        if e.entry.beside.pipelined:
            continue
        fed = [(k, p) for k in e.outputs for p in by_trigger.get(k, ())]
        e.kicks = tuple(fed)
        sub = getattr(e.entry.part, "subscribe", None)
        if not callable(sub) or not e.outputs:
            continue
        # a push source: its values go into Memory as they arrive, starting what they trigger and running the
        # react=True parts they feed at once (a camera frame, a command from the network)
        chain = react_chain(entries, set(e.outputs))
        if fed or chain:
            drive.work.push_sources.append((e, sub, Reaction(drive, chain) if chain else None))
    guard_entries(drive, tick, pipelines)
    return tuple(tick), pipelines


def guard_entries(drive: PipelineHost, tick: list[TickStep], pipelines: list[Pipeline]) -> None:
    """Give each part's run that needs one a fresh :class:`ReentryGuard` (every other ``None``), and put a
    :class:`GuardedTick` in a guarded part's place in the tick."""
    reacting = {id(r) for p in pipelines for r in p.react}
    reacting.update(
        id(r) for _e, _sub, reaction in drive.work.push_sources if reaction is not None for r in reaction.entries
    )
    guards = drive.work.reentry_guards
    guards.clear()
    for e in drive.runs:
        guard = ReentryGuard(drive, e) if needs_guard(e, reacting) else None
        e.reentry_guard = guard
        if guard is not None:
            guards.append(guard)
    for i, t in enumerate(tick):
        if isinstance(t, PartRun) and t.reentry_guard is not None:
            tick[i] = GuardedTick(t.reentry_guard)


def after_store(e: TickStep, origins: dict[str, float]) -> None:
    """Tell the pipelines triggered by ``e``'s outputs that they were written (called when ``e.kicks``)."""
    for k, p in e.kicks:
        p.new_value(origins.get(k))
