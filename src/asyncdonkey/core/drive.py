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
from ..safety.attach import attach_actuators, detach_actuators, start_safety_process
from .drive_report import format_report
from .drivestate import BackgroundWork, DriveLog, DriveSettings, StopLatch, TickCounters
from .partrun import PartRun
from .pipeline import Reaction, after_store, build_pipelines
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
    built by users.

    Its state is grouped by role (``asyncdonkey.core.drivestate``): :attr:`settings` (what the run asked for),
    :attr:`counters` (the timing state the report is made of), :attr:`stop_latch` (the stop request and its grace),
    :attr:`work` (what runs beside the ticks and shutdown takes down), :attr:`log` (rate-limited complaints about
    parts). What other modules read of it directly (the runs, the clock, what the loop thread is doing, the safety
    attachment) is named by the Protocols of ``asyncdonkey.core.runtypes``."""

    def __init__(
        self,
        entries: tuple[Entry, ...],
        mem: Memory,
        clock: Clock,
        loop: asyncio.AbstractEventLoop,
        profiler: Profiler,
        report: DriveReport,
        settings: DriveSettings,
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
        self.settings = settings
        #: ticking: true from the start of :meth:`run` until its ticks end (Donkeycar's flag)
        self.on = False
        # what the loop thread is doing (read by the watchdog thread): the step being called and since when
        self.current: TickStep | None = None
        self.part_started = math.inf
        #: the safety attachment (``asyncdonkey.safety.attach``): the in-process watchdog and the safety process,
        #: heartbeaten once a tick (None: none runs)
        self.watchdog: Watchdog | None = None
        self.safety_process: SafetyProcess | None = None
        #: waits for every tick's deadline (one OS timer per drive); closed by :meth:`run` when the ticks end
        self.waiter = DeadlineWaiter(loop, precise=settings.precise)
        #: the pieces of the drive's state by role (``asyncdonkey.core.drivestate``)
        self.counters = TickCounters()
        self.stop_latch = StopLatch(loop, settings.stop_grace_s, self)
        self.work = BackgroundWork()
        self.log = DriveLog()
        #: what each tick calls, in order: the parts' runs, a pipelined part's kicker or a guarded part's GuardedTick
        #: in its place (``asyncdonkey.core.pipeline``)
        self.tick_runs, self.work.pipelines = build_pipelines(self)
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

    # ------------------------------------------------------------------------------- read by others
    @property
    def stop_grace_s(self) -> float:
        """After a stop request, how long an awaited part may go on (the watchdog and the signal handler read it)."""
        return self.settings.stop_grace_s

    @property
    def loops(self) -> int:
        """Ticks run so far (live, for parts that report on the loop while it runs)."""
        return self.counters.loops

    @property
    def overruns(self) -> int:
        """Ticks so far that took longer than a period."""
        return self.counters.overruns

    @property
    def skipped(self) -> int:
        """Deadlines skipped so far because the loop was more than a period behind."""
        return self.counters.skipped

    @property
    def last_end(self) -> float:
        """When the latest tick ended, on the runtime clock."""
        return self.counters.last_end

    @property
    def t0(self) -> float | None:
        """The first tick's deadline (None until the background work starts)."""
        return self.counters.t0

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
            settings = self.settings
            self.safety_process = await start_safety_process(
                self, rate_hz, settings.want_safety_process, settings.exit_grace_s
            )
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
        error = self.work.error
        if error is not None:
            error.report = report
            raise error
        return report

    async def _end(self) -> bool:
        """Stop ticking, shut down, take the safety attachment off and fill the report; whether shutdown was
        cancelled."""
        if self.safety_process is not None:
            self.safety_process.ending()
        self.on = False
        self.waiter.close()
        self.work.unsubscribe_push_sources()
        try:
            return await shutdown_drive(self)
        finally:
            detach_actuators(self)
            self.fill_report()
            logger.info("%s", format_report(self.report, self.profiler))

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
        """Stop after the current tick. Safe from any thread and from a signal handler (:class:`StopLatch`)."""
        self.stop_latch.request(reason)

    # ------------------------------------------------------------------------------------- background
    def start_background(self, rate_hz: float) -> None:
        """Fix the first tick's deadline (:attr:`t0`) and start the parts' background work, whose ``update()``
        tasks see the drive's ticks as :func:`~asyncdonkey.clock.tick_grid` (a
        :class:`~asyncdonkey.poller.Poller` reads on them)."""
        self.counters.t0 = t0 = self.clock.now() + (0.0 if self.clock.is_virtual else START_MARGIN_S)
        period = 1.0 / rate_hz
        token = _TICK_GRID.set(TickGrid(t0, period, self.waiter.max_spin_s(period)))
        try:
            self._start_background()
        finally:
            _TICK_GRID.reset(token)

    def _start_background(self) -> None:
        work = self.work
        for p in work.pipelines:
            p.task = self.loop.create_task(p.main(), name=f"pipelined:{p.name}")
            work.tasks.append((p.entry, p.task))
        for source, subscribe, reaction in work.push_sources:
            if reaction is not None:
                reaction.task = self.loop.create_task(reaction.main(), name=f"react:{source.name}")
                work.tasks.append((source.entry, reaction.task))
            work.unsubscribe.append(
                subscribe(lambda value, origin, e=source, r=reaction: self._push_threadsafe(e, value, origin, r))
            )
        for r in self.runs:
            e = r.entry
            if e.beside.background is Background.THREAD:
                t = threading.Thread(target=self._thread_main, args=(r,), name=f"part:{e.name}", daemon=True)
                work.threads.append((e, t))
                t.start()
            elif e.beside.background is Background.TASK:
                task = self.loop.create_task(e.part.update(), name=f"part:{e.name}")
                task.add_done_callback(functools.partial(self._task_done, r))
                work.tasks.append((e, task))

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
            more = self.log.error_ready(e.name, self.clock.now())
            if more is not None:
                logger.error("part %r: %s failed: %r; continuing%s", e.name, what, exc, more)
            return
        err = PartError(e.name, None, f"{type(exc).__name__}: {exc}")
        err.__cause__ = exc
        if self.work.error is None:
            self.work.error = err
        logger.error("%s; stopping the vehicle", err)
        self.stop_latch.reason = "error"
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
        latch = self.stop_latch
        latch.task = asyncio.current_task()
        ticks = self._ticks(rate_hz, max_loop_count, duration, verbose, report_every)
        if any(e.awaits for e in self.tick_runs):
            await self._drive_from_task(ticks)
        else:
            await self._drive_from_timer(ticks, 1.0 / rate_hz)
        latch.reason = latch.reason or "stop()"

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
        part_failed, report_block, block_report_s = self._part_failed, self.log.blocked, self.settings.block_report_s
        counters, latch = self.counters, self.stop_latch
        sched, stop_at, end_at = self._schedule(rate_hz, max_loop_count, duration, end := now())
        period, loops, nan = sched.period, counters.loops, math.nan
        precise, beat = self.waiter.precise, self._start_heartbeat()  # precise: never on the virtual clock
        while not latch.requested:
            deadline = sched.deadline
            if loops >= stop_at or deadline >= end_at:
                self._limit_reached(loops >= stop_at)
                return
            if end < deadline:  # the last tick's end (or the start): early, so wait
                yield deadline
                if latch.requested:
                    return
            start = self._spin_until(deadline) if precise and end < deadline else now()  # precise: spin to it
            counters.last_start = t = start
            if beat is not None:
                beat(start)
            if loops == 0:
                counters.first_start = start
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
                    report_block(e.name, t_end - t, t_end)
                t = t_end
            self.current = None
            self.part_started = math.inf
            counters.last_end = end = now()
            buf[pos] = end
            commit()
            counters.loops = loops = loops + 1
            if end - start - period > _TIME_EPS:
                counters.overruns += 1
            if verbose:
                self._log_tick(end - start - period, end, loops, report_every)
            counters.skipped += sched.advance(end)  # more than a period behind: skipped and counted, never burst

    def _schedule(
        self, rate_hz: float, max_loop_count: int | None, duration: float | None, now: float
    ) -> tuple[Schedule, float, float]:
        """The ticks' deadlines from the first one (:attr:`t0`, or ``now`` when none was fixed), and the limits
        :meth:`_ticks` checks before each tick: the tick count to stop at and the deadline to stop at."""
        c = self.counters
        c.t0 = t0 = now if c.t0 is None else c.t0
        c.first_start = c.last_start = c.last_end = t0
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
        latch = self.stop_latch
        latch.reason = latch.reason or ("max_loop_count" if max_loops else "duration")

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
            latch = self.stop_latch
            if not latch.grace_cancel:
                raise exc
            latch.grace_cancel = False
            if latch.task is not None:
                latch.task.uncancel()
        t_end = self.clock.now()
        e.errors += 1
        if isinstance(exc, PartInterrupted):
            logger.error("%s", exc)
        return t_end

    def _log_tick(self, over: float, end: float, loops: int, report_every: int) -> None:
        """``verbose=True``, after each tick: a tick that took ``over`` seconds more than a period is warned of
        (rate-limited), and every ``report_every`` ticks the profiler's table is logged."""
        if over > _TIME_EPS:
            self.log.overrun(over, end)
        if report_every and loops % report_every == 0:
            logger.info("%s", self.profiler.table())

    async def _drive_from_timer(self, ticks: Generator[Any, Any, None], period: float) -> None:
        """Every tick runs from the deadline timer's callback; this task only waits for the drive to end.

        The future it waits on is also the drive's wake future: a stop request completes it (and the timer call is
        dropped), the last tick completes it, and an exception out of a tick (a part failing with
        ``on_error="stop"``) is set on it and raised here.
        """
        done = self.stop_latch.wake = self.loop.create_future()
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
        latch = self.stop_latch
        send, throw = ticks.send, ticks.throw
        try:
            step = send(None)
            while True:
                if step.__class__ is float:
                    if now() < step:
                        wake = latch.wake
                        if wake is None:  # one per drive: a stop request completes it, and then the drive ends
                            latch.wake = wake = loop.create_future()
                        if not latch.requested:
                            await waiter.wait_until(step, wake)
                    step = send(None)
                    continue
                try:  # anything raised here is the part's: thrown in where it is awaited, as its call's would be
                    if safety is not None:  # the loop is free while the part awaits: only its timeout bounds it
                        timeout = self.current.timeout if self.current is not None else None
                        safety.beat(math.inf if timeout is None else self.part_started + timeout)
                    latch.awaiting = step
                    result = await step
                except BaseException as exc:
                    latch.awaiting = None
                    step = throw(exc)
                else:
                    latch.awaiting = None
                    step = send(result)
        except StopIteration:
            return
        finally:
            ticks.close()

    def _part_failed(self, e: TickStep, tick: int, exc: Exception, now: float) -> None:
        e.errors += 1
        err = PartError(e.name, tick, f"{type(exc).__name__}: {exc}")
        if e.on_error == "stop":
            self.stop_latch.reason = "error"
            raise err from exc
        more = self.log.error_ready(e.name, now)
        if more is not None:
            logger.error("%s; continuing (on_error='continue')%s", err, more, exc_info=exc)

    # ----------------------------------------------------------------------------------------- report
    def fill_report(self) -> None:
        r, c, work = self.report, self.counters, self.work
        r.loops = c.loops
        r.overruns = c.overruns
        r.skipped_deadlines = c.skipped
        # from the first deadline, not the first start: a late first tick must not make the rate look higher
        # than asked (docs of DriveReport.achieved_hz)
        t0 = c.first_start if c.t0 is None else min(c.t0, c.first_start)
        r.elapsed_s = (c.last_end - t0) if c.loops else 0.0
        span = c.last_start - t0
        r.achieved_hz = (c.loops - 1) / span if c.loops > 1 and span > 0 else 0.0
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
        longest = self.log.longest_block
        if longest is not None:
            r.longest_block_ms = (longest[0] * 1e3, longest[1])
        r.shutdown_abandoned = list(work.abandoned)
        r.pipelined = {p.name: p.stats(r.elapsed_s) for p in work.pipelines}
        r.reentries_avoided = {g.name: g.stats() for g in work.reentry_guards}
        r.pushed = {e.name: reaction.stats() for e, _sub, reaction in work.push_sources if reaction is not None}
        r.stop_reason = r.stop_reason or self.stop_latch.reason or "stop()"
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
