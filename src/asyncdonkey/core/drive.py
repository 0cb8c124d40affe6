"""One drive: the state of a single ``Vehicle.run()``, from its first tick to its report.

A :class:`~asyncdonkey.loop.Vehicle` is the car's *definition* (its parts and channels) and can be driven
again and again; everything that belongs to one run lives here and is made fresh each time: the clock, the
profiler, the stop latch, the background tasks and ``update()`` threads, the watchdog, the counters the report is
made of, and for each part a :class:`~asyncdonkey.core.partrun.PartRun` (its error count, timing series, latency
recorder, pipeline kicks, re-entry guard, checked stores). The vehicle's entries (the plan ``add()`` made) are only
read. So a second run reports only itself and starts from the same plan, a ``stop()`` meant for one run cannot leak
into another, and every ending (done, stopped, failed, cancelled) fills the same report.

The drive owns its lifecycle (:meth:`Drive.run`): the safety attachment (the safety process, the watchdog and
each actuator wired to them, ``asyncdonkey.safety.attach``), the parts' background work, the ticks, the stop, the
two-phase shutdown (``asyncdonkey.core.shutdown``) and the report; ``Vehicle.run()`` makes a drive and awaits it.

The tick (:meth:`Drive.tick_loop`) is flat: for each part's run, check its run condition, read its inputs, call
it, store its outputs with their origins, record its time.

Timing goes into one row per tick of the drive's :class:`~asyncdonkey.core.profiler.TickTable`: the deadline and the
tick's start, each part's end time (one float store per part, ``nan`` for a part skipped by its run condition),
the tick's end. A part starts when the one before it ended, so one clock read per part is enough; lateness,
durations and overruns are worked out from the rows when a report asks.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
import logging
import math
import threading
from collections.abc import Callable, Generator
from typing import TYPE_CHECKING, Any

from ..clock import SPIN_BUDGET, Clock, DeadlineWaiter, Schedule, TickGrid
from ..clock import TICK_GRID as _TICK_GRID
from ..errors import PartError, PartInterrupted
from ..memory import Memory
from ..ratelimit import LogThrottle
from ..safety.attach import attach_actuators, detach_actuators, start_safety_process
from .drive_report import format_report
from .partrun import PartRun
from .pipeline import Reaction, ReentryGuard, after_store, build_pipelines
from .plan import Background, Entry, checked_store
from .profiler import Profiler, TableSeries, TickTable
from .runtypes import TickStep
from .shutdown import shutdown_drive

if TYPE_CHECKING:
    from ..contracts import Contracts
    from ..safety.process import SafetyProcess
    from ..safety.watchdog import Watchdog
    from .drive_report import DriveReport

__all__ = ["Drive"]

logger = logging.getLogger("asyncdonkey.loop")

#: On the real clock the first tick is due this long after the drive starts its background work: the parts'
#: tasks and threads start in between, and a :class:`~asyncdonkey.poller.Poller` reads its first sample on the
#: tick grid just before the first tick, which then has it (on the virtual clock the first tick is at once).
START_MARGIN_S = 0.005

#: Float noise in time arithmetic (0.4 + 0.2 = 0.6000000000000001) is not an overrun.
_TIME_EPS = 1e-9


class Drive:
    """One run, from its start to its report: made and awaited (:meth:`run`) by ``Vehicle.run()``; not meant to be
    built by users."""

    def __init__(
        self,
        entries: tuple[Entry, ...],
        mem: Memory,
        clock: Clock,
        loop: asyncio.AbstractEventLoop,
        profiler: Profiler,
        report: DriveReport,
        *,
        stop_grace_s: float,
        block_report_s: float,
        precise: bool = False,
        want_safety_process: bool | None = None,
        exit_grace_s: float | None = None,
    ) -> None:
        #: the vehicle's parts as added (the plan: never written by the drive)
        self.entries = entries
        #: each part's state for this drive, in the same order
        self.runs = tuple(PartRun(e) for e in entries)
        self.mem = mem
        self.clock = clock
        self.loop = loop
        self.profiler = profiler
        self.report = report
        self.stop_grace_s = stop_grace_s
        self.block_report_s = block_report_s
        #: ``Vehicle.safety_process``: None starts the safety process when it can, True requires it, False never
        self.want_safety_process = want_safety_process
        #: the exit grace the safety process enforces while the car's signal handlers are installed (else None)
        self.exit_grace_s = exit_grace_s
        # stop latch
        self.stop_requested = False
        self.stop_reason = ""
        self._wake: asyncio.Future[None] | None = None
        #: waits for every tick's deadline (one OS timer per drive); closed by :meth:`run` when the ticks end
        self.waiter = DeadlineWaiter(loop, precise=precise)
        self._grace_handle: asyncio.TimerHandle | None = None
        # background work owned by this run
        self.tasks: list[tuple[Entry, asyncio.Task[Any]]] = []
        self.threads: list[tuple[Entry, threading.Thread]] = []
        self.executor: concurrent.futures.ThreadPoolExecutor | None = None
        self.background_error: PartError | None = None
        self.on = False
        self.watchdog: Watchdog | None = None
        #: the safety process, heartbeaten once a tick (None: none runs)
        self.safety_process: SafetyProcess | None = None
        # what the loop thread is doing (read by the watchdog thread): the run (or tick stand-in) being called
        self.current: TickStep | None = None
        self.part_started = math.inf
        self._awaiting: Any = None
        self._grace_cancel = False
        self.task: asyncio.Task[Any] | None = None
        # counters (attributes, so any ending can fill the report)
        #: the first tick's deadline (None: at once), fixed by start_background()
        self.t0: float | None = None
        self.loops = 0
        self.overruns = 0
        self.skipped = 0
        self.first_start = self.last_start = self.last_end = 0.0
        self._errlog = LogThrottle(1.0)
        self._blocklog = LogThrottle(1.0)
        self._jitterlog = LogThrottle(1.0)
        self.longest_block: tuple[float, str] | None = None
        #: parts whose shutdown() or update() thread did not finish in time (left running as daemon threads)
        self.abandoned: list[str] = []
        # pipelined parts (asyncdonkey.core.pipeline): the tick calls their kickers in their place
        self.push_sources: list[tuple[PartRun, Any, Reaction | None]] = []
        self._unsubscribe: list[Any] = []
        #: the parts more than one path can be inside at once, one call at a time (asyncdonkey.core.pipeline)
        self.reentry_guards: list[ReentryGuard] = []
        #: what each tick calls, in order: the parts' runs, a pipelined part's kicker or a guarded part's GuardedTick
        #: in its place (``asyncdonkey.core.pipeline``)
        self.tick_runs, self.pipelines = build_pipelines(self)
        # the tick's timings: one row per tick (profiler.TickTable); a pipelined part's runs have a series
        self.table = table = TickTable(len(self.tick_runs), 1.0 / report.rate_hz, profiler.window)
        profiler.use_table(table)
        # a guarded part sits in the tick as its GuardedTick: its column is found through the GuardedTick's run
        column = {id(getattr(t, "run", t)): col for col, t in enumerate(self.tick_runs)}
        for r in self.runs:
            if r.entry.beside.pipelined:
                r.series = profiler.series_for(r.name)
            else:
                r.series = profiler.parts[r.name] = TableSeries(r.name, table, column[id(r)], skip_first=True)

    # ---------------------------------------------------------------------------------------- lifecycle
    async def run(
        self, max_loop_count: int | None, duration: float | None, verbose: bool, report_every: int
    ) -> DriveReport:
        """The whole drive: start (the safety attachment, then the parts' background work), tick until
        ``max_loop_count`` ticks, ``duration`` seconds, a stop request or cancellation, then stop, shut down
        (actuators to their safe state first) and fill the report, whatever ended it; the report is logged.

        Returns the report; raises what ended the drive, with the report attached to a :class:`PartError`
        (``.report``), or ``CancelledError`` when shutdown itself was cancelled."""
        report = self.report
        rate_hz = report.rate_hz
        self.on = True
        outcome: BaseException | None = None
        try:
            self.safety_process = await start_safety_process(self, rate_hz, self.want_safety_process, self.exit_grace_s)
            attach_actuators(
                self, {r.name: latency_recorder(self.profiler, r.name) for r in self.runs if r.entry.actuator}
            )
            self.start_background(rate_hz)
            await self.tick_loop(rate_hz, max_loop_count, duration, verbose, report_every)
        except BaseException as exc:
            outcome = exc
            report.stop_reason = "cancelled" if isinstance(exc, asyncio.CancelledError) else "error"
        cancelled = await self._end()
        if outcome is not None:
            if isinstance(outcome, PartError):
                outcome.report = report
            raise outcome
        if cancelled:
            raise asyncio.CancelledError()
        if self.background_error is not None:
            self.background_error.report = report
            raise self.background_error
        return report

    async def _end(self) -> bool:
        """Stop ticking, shut down, take the safety attachment off and fill the report; whether shutdown was
        cancelled."""
        if self.safety_process is not None:
            self.safety_process.ending()
        self.on = False
        self.waiter.close()
        self.unsubscribe_push_sources()
        try:
            return await shutdown_drive(self)
        finally:
            detach_actuators(self)
            self.fill_report()
            logger.info("%s", format_report(self.report, self.profiler))

    # ----------------------------------------------------------------------------------------- executor
    def get_executor(self) -> concurrent.futures.ThreadPoolExecutor:
        if self.executor is None:
            self.executor = concurrent.futures.ThreadPoolExecutor(
                max_workers=4, thread_name_prefix="asyncdonkey-offload"
            )
        return self.executor

    # ------------------------------------------------------------------------------------ checked mode
    def check_outputs(self, contracts: Contracts) -> int:
        """Checked mode for this drive: every part whose outputs have contracts stores through a check
        (:func:`~asyncdonkey.core.plan.checked_store`); returns how many parts are checked.

        Decided once, here, so the tick stays as it is: a checked part's run simply has another ``store``. Only
        the runs change: the entries keep their own stores, and the next drive decides again.
        """
        checked = 0
        for r in self.runs:
            store = checked_store(r.store, r.name, r.outputs, contracts)
            fixed = checked_store(r.store_fixed, r.name, r.outputs, contracts)
            if store is r.store and fixed is r.store_fixed:
                continue
            r.store, r.store_fixed = store, fixed
            checked += 1
        return checked

    # ---------------------------------------------------------------------------------------- stopping
    def request_stop(self, reason: str = "stop()") -> None:
        """Stop after the current tick. Safe from any thread and from a signal handler."""
        if not self.stop_requested:
            self.stop_requested = True
            self.stop_reason = self.stop_reason or reason
        loop = self.loop
        if not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._on_stop_requested)
            except RuntimeError:  # the loop closed in between
                pass

    def _on_stop_requested(self) -> None:
        w = self._wake
        if w is not None and not w.done():
            w.set_result(None)
        # an awaited part that does not return within the grace is cancelled, so a stop always ends the tick
        if self._grace_handle is None and self.on:
            self._grace_handle = self.loop.call_later(self.stop_grace_s, self._cancel_awaited_part)

    def _cancel_awaited_part(self) -> None:
        """Interrupt an awaited part that outlived the stop grace by cancelling the drive task at its await."""
        task = self.task
        if self._awaiting is not None and task is not None and not task.done():
            name = self.current.name if self.current is not None else "?"
            logger.error(
                "part %r did not return within %.1f s of the stop request: cancelling it", name, self.stop_grace_s
            )
            self._grace_cancel = True
            task.cancel()

    # ------------------------------------------------------------------------------------- background
    def start_background(self, rate_hz: float) -> None:
        """Fix the first tick's deadline (:attr:`t0`) and start the parts' background work, whose ``update()``
        tasks see the drive's ticks as :func:`~asyncdonkey.clock.tick_grid` (a
        :class:`~asyncdonkey.poller.Poller` reads on them)."""
        self.t0 = t0 = self.clock.now() + (0.0 if self.clock.is_virtual else START_MARGIN_S)
        period = 1.0 / rate_hz
        token = _TICK_GRID.set(TickGrid(t0, period, self.waiter.max_spin_s(period)))
        try:
            self._start_background()
        finally:
            _TICK_GRID.reset(token)

    def _start_background(self) -> None:
        for p in self.pipelines:
            p.task = self.loop.create_task(p.main(), name=f"pipelined:{p.name}")
            self.tasks.append((p.entry, p.task))
        for source, subscribe, reaction in self.push_sources:
            if reaction is not None:
                reaction.task = self.loop.create_task(reaction.main(), name=f"react:{source.name}")
                self.tasks.append((source.entry, reaction.task))
            self._unsubscribe.append(
                subscribe(lambda value, origin, e=source, r=reaction: self._push_threadsafe(e, value, origin, r))
            )
        for r in self.runs:
            e = r.entry
            if e.beside.background is Background.THREAD:
                t = threading.Thread(target=self._thread_main, args=(r,), name=f"part:{e.name}", daemon=True)
                self.threads.append((e, t))
                t.start()
            elif e.beside.background is Background.TASK:
                task = self.loop.create_task(e.part.update(), name=f"part:{e.name}")
                task.add_done_callback(functools.partial(self._task_done, r))
                self.tasks.append((e, task))

    def _push_threadsafe(self, e: PartRun, value: Any, origin: float, reaction: Reaction | None) -> None:
        try:
            self.loop.call_soon_threadsafe(self._pushed, e, value, origin, reaction)
        except RuntimeError:  # the loop has closed: the drive is over
            pass

    def _pushed(self, e: PartRun, value: Any, origin: float | None, reaction: Reaction | None) -> None:
        """A push source has a new value: into Memory now (not at the next tick), then start what it triggers
        and run the react=True parts it feeds."""
        if not self.on or value is None or e.store_fixed is None:
            return
        mem = self.mem
        now = self.clock.now()
        try:
            e.store_fixed(value, now if origin is None else origin, now)
        except Exception as exc:  # a value that does not fit the outputs: the part's error, as in a tick
            self.background_failed(e, exc, "push")
            return
        if e.kicks:
            after_store(e, mem.origins)
        if reaction is not None:
            reaction.kick()

    def unsubscribe_push_sources(self) -> None:
        for unsubscribe in self._unsubscribe:
            if callable(unsubscribe):
                unsubscribe()
        self._unsubscribe.clear()

    def _thread_main(self, e: PartRun) -> None:
        try:
            e.entry.part.update()
        except Exception as exc:
            try:
                self.loop.call_soon_threadsafe(self.background_failed, e, exc)
            except RuntimeError:
                logger.error("part %r background update() failed after the drive ended: %r", e.name, exc)

    def _task_done(self, e: PartRun, task: asyncio.Task[Any]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            self.background_failed(e, exc)

    def background_failed(self, e: PartRun, exc: BaseException, what: str = "background update()") -> None:
        """A part's work beside the ticks failed (its ``update()``, a pipelined or reacting run, a push):
        ``on_error="continue"`` (or a drive already ending) logs, rate-limited; ``"stop"`` stops the car with a
        :class:`PartError` that ``Vehicle.run()`` raises."""
        e.errors += 1
        if e.on_error == "continue" or not self.on:
            more = self._errlog.ready(e.name, self.clock.now(), "more errors")
            if more is not None:
                logger.error("part %r: %s failed: %r; continuing%s", e.name, what, exc, more)
            return
        err = PartError(e.name, None, f"{type(exc).__name__}: {exc}")
        err.__cause__ = exc
        if self.background_error is None:
            self.background_error = err
        logger.error("%s; stopping the vehicle", err)
        self.stop_reason = "error"
        self.request_stop("error")

    # ------------------------------------------------------------------------------------------ ticks
    async def tick_loop(
        self,
        rate_hz: float,
        max_loop_count: int | None,
        duration: float | None,
        verbose: bool,
        report_every: int,
    ) -> None:
        """Tick until a limit, a stop, an error or cancellation; counters are kept on ``self`` throughout.

        The ticks themselves are one generator (:meth:`_ticks`), flat, its hot names fast locals. It yields the
        next deadline when it has to wait, and an awaitable when a part's call must be awaited. Who drives it is
        decided here, once:

        * no part of the tick awaits (sync parts, pipelined kickers): the deadline timer's own loop callback
          resumes it (:meth:`DeadlineWaiter.call_at`), so a wake-up costs no task resume, no coroutine frames and
          no awaitable, which on a small board is most of what waking up costs;
        * otherwise this task resumes it: it waits for each deadline it yields and awaits each awaitable, sending
          the result back in (or throwing the exception in).
        """
        self.task = asyncio.current_task()
        ticks = self._ticks(rate_hz, max_loop_count, duration, verbose, report_every)
        if any(e.awaits for e in self.tick_runs):
            await self._drive_from_task(ticks)
        else:
            await self._drive_from_timer(ticks, 1.0 / rate_hz)
        self.stop_reason = self.stop_reason or "stop()"

    def _ticks(
        self, rate_hz: float, max_loop_count: int | None, duration: float | None, verbose: bool, report_every: int
    ) -> Generator[Any, Any, None]:
        """The drive's ticks: yields a deadline (float) to be resumed at, or an awaitable whose result (or exception)
        is to be sent (thrown) back in; returns when the drive is to end, the reason noted. Each tick fills a row
        of the :class:`~asyncdonkey.core.profiler.TickTable` (module docstring). Only what every tick does is here, on
        fast locals bound once; what is decided once, or rare (a limit, a part cut short, verbose logs), is a method.
        """
        now, entries, table = self.clock.now, self.tick_runs, self.table
        d, origins = self.mem.d, self.mem.origins
        buf, window, ncol, commit = table.buf, table.window, table.ncol, table.commit
        part_failed, report_block, block_report_s = self._part_failed, self._report_block, self.block_report_s
        sched, stop_at, end_at = self._schedule(rate_hz, max_loop_count, duration, end := now())
        period, loops, nan = sched.period, self.loops, math.nan
        precise, beat = self.waiter.precise, self._start_heartbeat()  # precise: never on the virtual clock
        while not self.stop_requested:
            deadline = sched.deadline
            if loops >= stop_at or deadline >= end_at:
                self._limit_reached(loops >= stop_at)
                return
            if end < deadline:  # the last tick's end (or the start): early, so wait
                yield deadline
                if self.stop_requested:
                    return
            start = self._spin_until(deadline) if precise and end < deadline else now()  # precise: spin to it
            self.last_start = t = start
            if beat is not None:
                beat(start)
            if loops == 0:
                self.first_start = start
            pos = (loops % window) * ncol
            buf[pos], buf[pos + 1] = deadline, start
            pos += 2
            table.begun = loops + 1

            for e in entries:
                cond = e.run_condition
                if cond is not None and not d.get(cond):  # skipped: writes nothing, its channels keep their origins
                    buf[pos] = nan
                    pos += 1
                    continue
                self.current = e
                self.part_started = t
                try:
                    args = e.args()
                    r = e.call(*args)
                    if e.awaits:  # awaited by the drive task (:meth:`_drive_from_task`), the result sent back
                        r = yield r
                    t_end = now()
                    if r is not None and e.store is not None:
                        e.store(r, args, t_end)
                        if e.kicks:
                            after_store(e, origins)
                except Exception as exc:
                    t_end = now()
                    part_failed(e, loops, exc, t_end)
                except (asyncio.CancelledError, PartInterrupted) as exc:
                    t_end = self._cut_short(e, exc)
                buf[pos] = t_end
                pos += 1
                if e.latency is not None:
                    e.latency(t_end)
                if t_end - t > block_report_s and e.is_sync_inline:
                    report_block(e, t_end - t, t_end)
                t = t_end
            self.current = None
            self.part_started = math.inf
            self.last_end = end = now()
            buf[pos] = end
            commit()
            self.loops = loops = loops + 1
            if end - start - period > _TIME_EPS:
                self.overruns += 1
            if verbose:
                self._log_tick(end - start - period, end, loops, report_every)
            self.skipped += sched.advance(end)  # more than a period behind: skipped and counted, never burst

    def _schedule(
        self, rate_hz: float, max_loop_count: int | None, duration: float | None, now: float
    ) -> tuple[Schedule, float, float]:
        """The ticks' deadlines from the first one (:attr:`t0`, or ``now`` when none was fixed), and the limits
        :meth:`_ticks` checks before each tick: the tick count to stop at and the deadline to stop at."""
        self.t0 = t0 = now if self.t0 is None else self.t0
        self.first_start = self.last_start = self.last_end = t0
        stop_at = math.inf if max_loop_count is None else max_loop_count
        end_at = math.inf if duration is None else t0 + duration
        return Schedule(rate_hz, t0), stop_at, end_at

    def _start_heartbeat(self) -> Callable[[float], None] | None:
        """Tell the safety process the ticks begin; its heartbeat, called once a tick (None: no safety process)."""
        if self.safety_process is None:
            return None
        self.safety_process.ticking()
        return self.safety_process.beat

    def _limit_reached(self, max_loops: bool) -> None:
        """The drive ends before its next tick: its tick count is done (``max_loops``) or its duration is up."""
        self.stop_reason = self.stop_reason or ("max_loop_count" if max_loops else "duration")

    def _spin_until(self, deadline: float) -> float:
        """Precise mode: the deadline timer called back early; spin the last stretch. Returns the tick's start.

        The waiter learns its spin window from when the tick got here."""
        now = self.clock.now
        start = now()
        self.waiter.arrived(start)
        while start < deadline:
            start = now()
        return start

    def _cut_short(self, e: TickStep, exc: asyncio.CancelledError | PartInterrupted) -> float:
        """Part ``e`` was cut short by a stop request's grace: cancelled at its await, or interrupted inside its
        sync call. The part failed (counted, an interruption logged), the stop goes on. Returns its end time.

        A cancellation that is not the grace's (our caller cancelled the drive) is raised on."""
        if isinstance(exc, asyncio.CancelledError):
            if not self._grace_cancel:
                raise exc
            self._grace_cancel = False
            if self.task is not None:
                self.task.uncancel()
        t_end = self.clock.now()
        e.errors += 1
        if isinstance(exc, PartInterrupted):
            logger.error("%s", exc)
        return t_end

    def _log_tick(self, over: float, end: float, loops: int, report_every: int) -> None:
        """``verbose=True``, after each tick: a tick that took ``over`` seconds more than a period is warned of
        (rate-limited), and every ``report_every`` ticks the profiler's table is logged."""
        if over > _TIME_EPS:
            more = self._jitterlog.ready("jitter", end)
            if more is not None:
                logger.warning("jitter violation in vehicle loop with %.0f ms overrun%s", over * 1e3, more)
        if report_every and loops % report_every == 0:
            logger.info("%s", self.profiler.table())

    async def _drive_from_timer(self, ticks: Generator[Any, Any, None], period: float) -> None:
        """Every tick runs from the deadline timer's callback; this task only waits for the drive to end.

        The future it waits on is also the drive's wake future: a stop request completes it (and the timer call is
        dropped), the last tick completes it, and an exception out of a tick (a part failing with
        ``on_error="stop"``) is set on it and raised here.
        """
        done = self._wake = self.loop.create_future()
        resume = ticks.send

        def on_deadline() -> float | None:
            """Run the ticks due now; return the deadline to be called back at, or None when the drive ends."""
            if done.done():  # the drive was cancelled (or stopped) while this call was queued
                return None
            try:
                return resume(None)  # type: ignore[no-any-return]
            except StopIteration:
                done.set_result(None)
            except BaseException as exc:  # the drive's error: raised by the waiting task, after the safe state
                done.set_exception(exc)
            return None

        deadline = on_deadline()  # the first tick is due at once
        waiter = self.waiter
        if deadline is not None:
            # the ticks spin precise mode's last stretch themselves, and are mostly a period apart
            waiter.call_at(deadline, on_deadline, early=True, period=period)
        try:
            await done
        finally:
            waiter.cancel_call()
            ticks.close()

    async def _drive_from_task(self, ticks: Generator[Any, Any, None]) -> None:
        """This task resumes the ticks: it waits for each deadline they yield and awaits each awaitable.

        An awaitable is the call of the part now running (:attr:`current`): while it is awaited it is
        :attr:`_awaiting` (what the stop grace cancels), and the loop is free, so the safety process's heartbeat
        is pushed to the part's timeout (none: no bound but the part's own)."""
        loop = self.loop
        now = self.clock.now
        waiter = self.waiter
        safety = self.safety_process
        send, throw = ticks.send, ticks.throw
        try:
            step = send(None)
            while True:
                if step.__class__ is float:
                    if now() < step:
                        wake = self._wake
                        if wake is None:  # one per drive: a stop request completes it, and then the drive ends
                            self._wake = wake = loop.create_future()
                        if not self.stop_requested:
                            await waiter.wait_until(step, wake)
                    step = send(None)
                    continue
                try:  # anything raised here is the part's: thrown in where it is awaited, as its call's would be
                    if safety is not None:  # the loop is free while the part awaits: only its timeout bounds it
                        timeout = self.current.timeout if self.current is not None else None
                        safety.beat(math.inf if timeout is None else self.part_started + timeout)
                    self._awaiting = step
                    result = await step
                except BaseException as exc:
                    self._awaiting = None
                    step = throw(exc)
                else:
                    self._awaiting = None
                    step = send(result)
        except StopIteration:
            return
        finally:
            ticks.close()

    def _part_failed(self, e: TickStep, tick: int, exc: Exception, now: float) -> None:
        e.errors += 1
        err = PartError(e.name, tick, f"{type(exc).__name__}: {exc}")
        if e.on_error == "stop":
            self.stop_reason = "error"
            raise err from exc
        more = self._errlog.ready(e.name, now, "more errors")
        if more is not None:
            logger.error("%s; continuing (on_error='continue')%s", err, more, exc_info=exc)

    def _report_block(self, e: TickStep, blocked: float, now: float) -> None:
        """A sync part held the loop thread past the failsafe window: name it (the watchdog covered the car)."""
        if self.longest_block is None or blocked > self.longest_block[0]:
            self.longest_block = (blocked, e.name)
        more = self._blocklog.ready(e.name, now)
        if more is not None:
            logger.warning(
                "loop blocked %s ms by part %r (a sync run() on the loop thread; add it with executor=True if it "
                "can block)%s",
                f"{blocked * 1e3:,.0f}",
                e.name,
                more,
            )

    # ----------------------------------------------------------------------------------------- report
    def fill_report(self) -> None:
        r = self.report
        r.loops = self.loops
        r.overruns = self.overruns
        r.skipped_deadlines = self.skipped
        # from the first deadline, not the first start: a late first tick must not make the rate look higher
        # than asked (docs of DriveReport.achieved_hz)
        t0 = self.first_start if self.t0 is None else min(self.t0, self.first_start)
        r.elapsed_s = (self.last_end - t0) if self.loops else 0.0
        span = self.last_start - t0
        r.achieved_hz = (self.loops - 1) / span if self.loops > 1 and span > 0 else 0.0
        stats = self.profiler.as_dict()
        r.parts = stats["parts"]
        r.lateness_ms = stats["loop"]["lateness"] or {}
        r.overrun_ms = stats["loop"]["overrun"] or {}
        r.latency_ms = {name: s for name, s in stats["latency"].items() if s is not None}
        r.part_errors = {p.name: p.errors for p in self.runs if p.errors}
        if self.watchdog is not None:
            r.watchdog_events = self.watchdog.events
            r.watchdog_failed_attempts = self.watchdog.failed_attempts
        for e in self.entries:
            unsafe = getattr(e.part, "unsafe", None) if e.actuator else None
            if unsafe is not None and unsafe.events:
                r.unsafe_ms[e.name] = unsafe.as_dict()
        if self.safety_process is not None:
            r.safety_process = self.safety_process.summary
        if self.longest_block is not None:
            r.longest_block_ms = (self.longest_block[0] * 1e3, self.longest_block[1])
        r.shutdown_abandoned = list(self.abandoned)
        r.pipelined = {p.name: p.stats(r.elapsed_s) for p in self.pipelines}
        r.reentries_avoided = {g.name: g.stats() for g in self.reentry_guards}
        r.pushed = {e.name: reaction.stats() for e, _sub, reaction in self.push_sources if reaction is not None}
        r.stop_reason = r.stop_reason or self.stop_reason or "stop()"
        if self.waiter.precise:  # the window as armed: at most its budget of the period
            window = self.waiter.spin_window_s
            r.spin_window_ms = (min(window, SPIN_BUDGET / r.rate_hz) if r.rate_hz > 0 else window) * 1e3
            r.precise_sleeps = self.waiter.sleeps


def latency_recorder(profiler: Profiler, name: str) -> Callable[[float, float], None]:
    """``record(t, origin)``: the command sensed at ``origin`` reached actuator ``name``'s output at ``t``.

    Counted once per command: a tick that re-applies a command already on the output (same origin: the pilot has
    not published since) is not a new actuation, and counting it would inflate the figure with the idle time.
    """
    rec = profiler.latency_for(name).record
    last: list[float | None] = [None]

    def record(t: float, origin: float) -> None:
        if origin != last[0]:
            last[0] = origin
            rec(t - origin)

    return record
