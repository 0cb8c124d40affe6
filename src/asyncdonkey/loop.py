"""The drive loop: :class:`Vehicle` runs parts in order at ``rate_hz`` on monotonic deadlines.

Design notes (see DESIGN.md §1):

* **Deadlines, not sleeps.** Tick ``k`` is due at ``t0 + k / rate_hz`` on the runtime clock. Donkeycar sleeps
  ``1/rate_hz - elapsed`` from each tick's own start, so every tick's scheduling error accumulates and its
  loop drifts (-0.7 % at 20 Hz, -17 % at 1 kHz). Absolute deadlines cannot drift.
* **No catch-up bursts.** After an overrun the next tick starts at once; when the loop is more than a period
  behind, the missed deadlines are skipped and counted instead of being run back to back.
* **Decided at add().** How a part is called (inline, awaited, offloaded, threaded) is worked out once in
  :meth:`Vehicle.add`; each tick only walks a list of prepared entries.
* **One clock.** All timing comes from :func:`asyncdonkey.clock.get_clock` for the loop ``run()`` runs on, so
  on :class:`asyncdonkey.testing.VirtualClockLoop` the whole drive is virtual and deterministic.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import inspect
import logging
import math
import signal
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from .clock import Clock, get_clock
from .memory import Memory
from .profiler import Profiler
from .ratelimit import LogThrottle

__all__ = ["DriveReport", "OutputCountError", "PartError", "PartSpecError", "Vehicle"]

logger = logging.getLogger(__name__)

OnError = Literal["stop", "continue"]
AGE_SUFFIX = "@age"
#: Float noise in time arithmetic (0.4 + 0.2 = 0.6000000000000001) is not an overrun.
_TIME_EPS = 1e-9
_TICK_EPS = 1e-6  # in periods: a deadline this close to `now` counts as passed


class PartSpecError(ValueError):
    """``Vehicle.add`` was given something that cannot run; the message names the part and the argument."""


class OutputCountError(ValueError):
    """A part returned a value that does not unpack into its declared outputs."""


class PartError(RuntimeError):
    """A part failed while driving. ``part`` names it, ``tick`` is the loop count it failed on (0-based)."""

    def __init__(self, part: str, tick: int | None, message: str) -> None:
        where = f" on tick {tick}" if tick is not None else " in its background task"
        super().__init__(f"part {part!r} failed{where}: {message}")
        self.part = part
        self.tick = tick


@dataclass
class DriveReport:
    """What one drive did. Times are seconds on the runtime clock unless the name says ``_ms``.

    Attributes:
        loops: ticks run.
        elapsed_s: from the start of the first tick to the end of the last.
        achieved_hz: ``(loops - 1) / (last tick start - first tick start)``; equals ``rate_hz`` when every
            tick starts on its deadline.
        rate_hz: the requested rate.
        overruns: ticks that took longer than one period.
        skipped_deadlines: deadlines dropped because the loop was more than a period behind.
        lateness_ms: percentiles of (tick start - its deadline): keys ``max, min, avg, 50%, 90%, 99%, 99.9%``.
        overrun_ms: the same for ``max(0, tick duration - period)``.
        parts: per-part timing summaries in ms (Donkeycar's columns), by part name.
        part_errors: errors caught and survived under ``on_error="continue"``, by part name.
        stop_reason: ``"max_loop_count"``, ``"duration"``, ``"stop()"``, ``"cancelled"`` or ``"error"``.
    """

    loops: int = 0
    elapsed_s: float = 0.0
    achieved_hz: float = 0.0
    rate_hz: float = 0.0
    overruns: int = 0
    skipped_deadlines: int = 0
    lateness_ms: dict[str, float] = field(default_factory=dict)
    overrun_ms: dict[str, float] = field(default_factory=dict)
    parts: dict[str, dict[str, float] | None] = field(default_factory=dict)
    part_errors: dict[str, int] = field(default_factory=dict)
    stop_reason: str = ""

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class _Entry:
    """One part as the tick sees it; everything here is decided in ``Vehicle.add``."""

    __slots__ = (
        "args",
        "awaits",
        "call",
        "errors",
        "executor",
        "inputs",
        "name",
        "on_error",
        "outputs",
        "part",
        "run_condition",
        "series",
        "shutdown_timeout",
        "store",
        "threaded",
    )

    def __init__(self) -> None:
        self.errors = 0


class Vehicle:
    """Runs parts in order, ``rate_hz`` times a second, passing values through :attr:`mem`.

    Drop-in for Donkeycar's ``Vehicle``: ``add(part, inputs, outputs, threaded, run_condition)`` and
    ``start(rate_hz, max_loop_count, verbose)`` behave as Donkeycar users know them. :meth:`run` is the same
    loop as a coroutine, for embedding in an asyncio application or a test on the virtual clock.
    """

    def __init__(self, mem: Memory | None = None, *, profiler_window: int | None = None) -> None:
        self.mem = mem if mem is not None else Memory()
        self.profiler = Profiler() if profiler_window is None else Profiler(profiler_window)
        self.parts: list[_Entry] = []
        self.on = False
        self._stop_requested = False
        self._stop_reason = ""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Future[None] | None = None
        self._threads: list[tuple[_Entry, threading.Thread]] = []
        self._tasks: list[tuple[_Entry, asyncio.Task[Any]]] = []
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._background_error: PartError | None = None
        self._running = False
        self._errlog = LogThrottle(1.0)
        self._age_now: Callable[[], float] = self.mem._now

    @classmethod
    def from_donkeycar(cls, dk_vehicle: Any) -> Vehicle:
        """A Vehicle with the same parts, channels and memory contents as a Donkeycar ``Vehicle``.

        Lets an existing ``manage.py``-style builder run on this loop unchanged: build the Donkeycar vehicle as
        before, then drive ``Vehicle.from_donkeycar(v)``.
        """
        v = cls()
        v.mem.update(dict(getattr(dk_vehicle.mem, "d", {})))
        for entry in dk_vehicle.parts:
            v.add(
                entry["part"],
                inputs=list(entry.get("inputs") or []),
                outputs=list(entry.get("outputs") or []),
                threaded=entry.get("thread") is not None,
                run_condition=entry.get("run_condition") or None,
            )
        return v

    # ------------------------------------------------------------------------------------------ add()
    def add(
        self,
        part: Any,
        inputs: Sequence[str] = (),
        outputs: Sequence[str] = (),
        threaded: bool = False,
        run_condition: str | None = None,
        *,
        executor: bool = False,
        on_error: OnError = "stop",
        name: str | None = None,
        shutdown_timeout: float = 2.0,
    ) -> None:
        """Add ``part`` to the end of the drive loop.

        Args:
            part: an object with ``run(*inputs)`` (sync or ``async``), or with ``update()`` plus
                ``run_threaded(*inputs)`` when ``threaded``. An ``async def update(self)`` always runs as a
                background task beside the ticks.
            inputs: channel names read from :attr:`mem` and passed positionally. A name ending in ``@age``
                (``"user/throttle@age"``) passes the seconds since that channel was last written instead.
            outputs: channel names the returned value is written to. ``None`` writes nothing; one output
                stores the value as is; several unpack it (a count mismatch is an error).
            threaded: Donkeycar's threaded part: a sync ``update()`` loop runs in its own thread and
                ``run_threaded()`` is called each tick.
            run_condition: a channel name; the part runs only on ticks where that channel is truthy.
            executor: run a sync ``run`` in a worker thread, still awaited in order (heavy compute).
            on_error: ``"stop"`` (default) stops the car and raises :class:`PartError` from ``run()``;
                ``"continue"`` logs (rate-limited), counts and carries on.
            name: the name used in reports and errors (default: the part's class name, made unique).
            shutdown_timeout: seconds allowed for this part's ``shutdown()``.
        """
        label = name or type(part).__name__
        where = f"Vehicle.add({label})"
        if self._running:
            raise PartSpecError(f"{where}: parts cannot be added while the vehicle is running")
        ins = _channel_list(inputs, "inputs", where)
        outs = _channel_list(outputs, "outputs", where)
        for o in outs:
            if o.endswith(AGE_SUFFIX):
                raise PartSpecError(f"{where}: output {o!r} ends in {AGE_SUFFIX!r}, which is for inputs only")
        if type(threaded) is not bool:
            raise PartSpecError(f"{where}: threaded must be True or False, got {threaded!r}")
        if type(executor) is not bool:
            raise PartSpecError(f"{where}: executor must be True or False, got {executor!r}")
        if run_condition is not None and (not isinstance(run_condition, str) or not run_condition):
            raise PartSpecError(f"{where}: run_condition must be a channel name (str), got {run_condition!r}")
        if on_error not in ("stop", "continue"):
            raise PartSpecError(f"{where}: on_error must be 'stop' or 'continue', got {on_error!r}")
        if not (isinstance(shutdown_timeout, int | float) and shutdown_timeout > 0):
            raise PartSpecError(f"{where}: shutdown_timeout must be a positive number, got {shutdown_timeout!r}")

        update = getattr(part, "update", None)
        async_update = inspect.iscoroutinefunction(update)
        if threaded:
            if update is None or not callable(update):
                raise PartSpecError(f"{where}: threaded=True needs an update() method, {label} has none")
            fn = getattr(part, "run_threaded", None)
            method = "run_threaded"
            if fn is None and async_update:
                fn, method = getattr(part, "run", None), "run"
            if fn is None or not callable(fn):
                raise PartSpecError(f"{where}: threaded=True needs a run_threaded() method, {label} has none")
        else:
            fn = getattr(part, "run", None)
            method = "run"
            if fn is None or not callable(fn):
                raise PartSpecError(
                    f"{where}: a part needs a run() method (or threaded=True with update()"
                    f" and run_threaded()); {label} has none"
                )
        is_coro = inspect.iscoroutinefunction(fn)
        if executor and is_coro:
            raise PartSpecError(f"{where}: executor=True is for a sync {method}(); {label}.{method} is async")
        _check_arity(fn, len(ins), where, method)

        e = _Entry()
        e.part = part
        e.name = self._unique_name(label)
        e.inputs = ins
        e.outputs = outs
        e.run_condition = run_condition
        e.on_error = on_error
        e.shutdown_timeout = float(shutdown_timeout)
        e.threaded = "thread" if threaded and not async_update else ("task" if async_update else None)
        e.executor = executor
        e.awaits = is_coro or executor
        e.call = self._offload(fn) if executor else fn
        e.args = self._arg_getter(ins)
        e.store = self._storer(outs)
        e.series = self.profiler.series_for(e.name)
        self.parts.append(e)
        logger.debug("added part %s inputs=%s outputs=%s", e.name, ins, outs)

    def _unique_name(self, label: str) -> str:
        names = {e.name for e in self.parts}
        if label not in names:
            return label
        n = 2
        while f"{label}#{n}" in names:
            n += 1
        return f"{label}#{n}"

    def _arg_getter(self, ins: tuple[str, ...]) -> Callable[[], Sequence[Any]]:
        d = self.mem.d
        if not ins:
            empty: tuple[Any, ...] = ()
            return lambda: empty
        if not any(i.endswith(AGE_SUFFIX) for i in ins):
            dget = d.get
            if len(ins) == 1:
                (k,) = ins
                return lambda: (dget(k),)
            return lambda: list(map(dget, ins))
        stamps = self.mem.stamps
        inf = math.inf
        plan = tuple((i[: -len(AGE_SUFFIX)], True) if i.endswith(AGE_SUFFIX) else (i, False) for i in ins)

        def get_with_ages() -> list[Any]:
            now = self._age_now()
            return [(now - stamps.get(k, now - inf)) if is_age else d.get(k) for k, is_age in plan]

        return get_with_ages

    def _storer(self, outs: tuple[str, ...]) -> Callable[[Any, float], None] | None:
        d, stamps = self.mem.d, self.mem.stamps
        if not outs:
            return None
        if len(outs) == 1:
            (k,) = outs

            def store_one(value: Any, now: float) -> None:
                d[k] = value
                stamps[k] = now

            return store_one
        n = len(outs)

        def store_many(values: Any, now: float) -> None:
            try:
                count = len(values)
            except TypeError:
                raise OutputCountError(
                    f"returned {type(values).__name__} for {n} outputs {list(outs)};"
                    f" expected a tuple or list of {n} values"
                ) from None
            if count != n:
                raise OutputCountError(f"returned {count} values for {n} outputs {list(outs)}")
            for k, v in zip(outs, values, strict=True):
                d[k] = v
                stamps[k] = now

        return store_many

    def _offload(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        def offloaded(*args: Any) -> asyncio.Future[Any]:
            loop = asyncio.get_running_loop()
            if self._executor is None:
                self._executor = concurrent.futures.ThreadPoolExecutor(
                    max_workers=4, thread_name_prefix="asyncdonkey-offload"
                )
            return loop.run_in_executor(self._executor, fn, *args)

        return offloaded

    # ------------------------------------------------------------------------------------------ stop()
    def stop(self) -> None:
        """Ask the drive loop to stop: the current tick finishes, then shutdown runs.

        Safe from any thread and from a signal handler: it sets a flag and wakes the loop through
        ``call_soon_threadsafe``.
        """
        if not self._stop_requested:
            self._stop_requested = True
            self._stop_reason = self._stop_reason or "stop()"
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(_set_done, wake)

    # ------------------------------------------------------------------------------------------- run()
    async def run(
        self,
        rate_hz: float = 20,
        max_loop_count: int | None = None,
        *,
        duration: float | None = None,
        verbose: bool = False,
        report_every: int = 200,
    ) -> DriveReport:
        """Drive until ``max_loop_count`` ticks, ``duration`` seconds, :meth:`stop` or cancellation.

        Installs no signal handlers and never touches the event loop policy, so it can run inside any asyncio
        application. Cancelling the task that awaits it shuts the vehicle down cleanly before the
        ``CancelledError`` propagates. Returns a :class:`DriveReport`; raises :class:`PartError` when a part
        with ``on_error="stop"`` fails (after shutdown has run).
        """
        if not (isinstance(rate_hz, int | float) and rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"Vehicle.run: rate_hz must be a positive number, got {rate_hz!r}")
        if max_loop_count is not None and (not isinstance(max_loop_count, int) or max_loop_count < 0):
            raise ValueError(f"Vehicle.run: max_loop_count must be a non-negative int, got {max_loop_count!r}")
        if self._running:
            raise RuntimeError("Vehicle.run: this vehicle is already running")
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        self._loop = loop
        self._running = True
        self.on = True
        self._stop_requested = False
        self._stop_reason = ""
        self.mem.use_clock(clock.now)
        self._age_now = clock.now
        report = DriveReport(rate_hz=float(rate_hz))
        error: BaseException | None = None
        try:
            self._start_background(loop)
            await self._drive(clock, float(rate_hz), max_loop_count, duration, verbose, report_every, report)
        except asyncio.CancelledError:
            report.stop_reason = "cancelled"
            raise
        except BaseException as exc:
            report.stop_reason = "error"
            error = exc
            raise
        finally:
            self.on = False
            await self._shutdown()
            self._fill_report(report)
            self._running = False
            self._wake = None
            logger.info("%s", self.format_report(report))
            if error is None and self._background_error is not None and report.stop_reason != "cancelled":
                err, self._background_error = self._background_error, None
                raise err
        return report

    def _start_background(self, loop: asyncio.AbstractEventLoop) -> None:
        self._threads = []
        self._tasks = []
        self._background_error = None
        for e in self.parts:
            if e.threaded == "thread":
                t = threading.Thread(target=self._thread_main, args=(e,), name=f"part:{e.name}", daemon=True)
                self._threads.append((e, t))
                t.start()
            elif e.threaded == "task":
                task = loop.create_task(e.part.update(), name=f"part:{e.name}")
                task.add_done_callback(lambda t, e=e: self._task_done(e, t))
                self._tasks.append((e, task))

    def _thread_main(self, e: _Entry) -> None:
        try:
            e.part.update()
        except Exception as exc:
            self._background_failed(e, exc)

    def _task_done(self, e: _Entry, task: asyncio.Task[Any]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            self._background_failed(e, exc)

    def _background_failed(self, e: _Entry, exc: BaseException) -> None:
        e.errors += 1
        if e.on_error == "continue" or not self.on:
            logger.error("part %r background update() failed: %r", e.name, exc)
            return
        err = PartError(e.name, None, f"{type(exc).__name__}: {exc}")
        err.__cause__ = exc
        if self._background_error is None:
            self._background_error = err
        logger.error("%s; stopping the vehicle", err)
        self._stop_reason = "error"
        self.stop()

    async def _drive(
        self,
        clock: Clock,
        rate_hz: float,
        max_loop_count: int | None,
        duration: float | None,
        verbose: bool,
        report_every: int,
        report: DriveReport,
    ) -> None:
        loop = asyncio.get_running_loop()
        now = clock.now
        period = 1.0 / rate_hz
        entries = tuple(self.parts)
        d = self.mem.d
        lateness_rec = self.profiler.lateness.record
        overrun_rec = self.profiler.overrun.record
        tick_rec = self.profiler.tick.record
        jitter_log = LogThrottle(1.0)
        loops = 0
        overruns = 0
        skipped = 0
        t0 = now()
        end_at = None if duration is None else t0 + duration
        k = 0
        first_start = last_start = last_end = t0
        while not self._stop_requested:
            if max_loop_count is not None and loops >= max_loop_count:
                self._stop_reason = self._stop_reason or "max_loop_count"
                break
            deadline = t0 + k / rate_hz
            if end_at is not None and deadline >= end_at:
                self._stop_reason = self._stop_reason or "duration"
                break
            if now() < deadline:
                self._wake = wake = loop.create_future()
                if self._stop_requested:  # stop() raced with the new future
                    break
                await clock.sleep_until(deadline, wake)
                if self._stop_requested:
                    break
            start = now()
            if loops == 0:
                first_start = start
            last_start = start
            lateness_rec(start - deadline)

            for e in entries:
                cond = e.run_condition
                if cond is not None and not d.get(cond):
                    continue
                t = now()
                try:
                    r = e.call(*e.args())
                    if e.awaits:
                        r = await r
                    t_end = now()
                    if r is not None and e.store is not None:
                        e.store(r, t_end)
                except asyncio.CancelledError:
                    raise
                except Exception as exc:
                    t_end = now()
                    self._part_failed(e, loops, exc, t_end)
                e.series.record(t_end - t)

            last_end = end = now()
            loops += 1
            dur = end - start
            over = dur - period
            if over > _TIME_EPS:
                overruns += 1
                overrun_rec(over)
                if verbose and jitter_log.allow("jitter", end):
                    held = jitter_log.take_suppressed("jitter")
                    more = f" ({held} more since the last warning)" if held else ""
                    logger.warning("jitter violation in vehicle loop with %.0f ms overrun%s", over * 1e3, more)
            else:
                overrun_rec(0.0)
            tick_rec(dur)
            if verbose and report_every and loops % report_every == 0:
                logger.info("%s", self.profiler.table())
            k += 1
            # more than a period behind: skip the missed deadlines instead of bursting to catch up
            # (float noise of a few ulps is neither "behind" nor "not yet passed")
            if end - (t0 + k / rate_hz) > period + _TIME_EPS:
                behind_k = math.floor((end - t0) * rate_hz + _TICK_EPS)
                skipped += behind_k - k
                k = behind_k
        report.loops = loops
        report.overruns = overruns
        report.skipped_deadlines = skipped
        report.elapsed_s = (last_end - first_start) if loops else 0.0
        report.achieved_hz = (loops - 1) / (last_start - first_start) if loops > 1 and last_start > first_start else 0.0
        report.stop_reason = self._stop_reason or "stop()"

    def _part_failed(self, e: _Entry, tick: int, exc: Exception, now: float) -> None:
        e.errors += 1
        err = PartError(e.name, tick, f"{type(exc).__name__}: {exc}")
        if e.on_error == "stop":
            self._stop_reason = "error"
            raise err from exc
        if self._errlog.allow(e.name, now):
            held = self._errlog.take_suppressed(e.name)
            more = f" ({held} more errors since the last report)" if held else ""
            logger.error("%s; continuing (on_error='continue')%s", err, more, exc_info=exc)

    # -------------------------------------------------------------------------------------- shutdown
    async def _shutdown(self) -> None:
        """Shut every part down exactly once, then cancel tasks and join threads, all with timeouts."""
        loop = asyncio.get_running_loop()
        for e in self.parts:
            fn = getattr(e.part, "shutdown", None)
            if fn is None or not callable(fn):
                continue
            try:
                if inspect.iscoroutinefunction(fn):
                    await asyncio.wait_for(fn(), e.shutdown_timeout)
                else:
                    await asyncio.wait_for(asyncio.shield(loop.run_in_executor(None, fn)), e.shutdown_timeout)
            except TimeoutError:
                logger.error("part %r: shutdown() did not finish within %.1f s", e.name, e.shutdown_timeout)
            except asyncio.CancelledError:
                logger.error("part %r: shutdown() was cancelled", e.name)
            except Exception as exc:
                logger.error("part %r: shutdown() raised %r", e.name, exc, exc_info=exc)
        for _, task in self._tasks:
            task.cancel()
        for e, task in self._tasks:
            try:
                await asyncio.wait_for(task, e.shutdown_timeout)
            except (asyncio.CancelledError, TimeoutError):
                pass
            except Exception:
                pass  # already reported by _task_done
        for e, t in self._threads:
            await loop.run_in_executor(None, t.join, e.shutdown_timeout)
            if t.is_alive():
                logger.error(
                    "part %r: update() thread still running %.1f s after shutdown()",
                    e.name,
                    e.shutdown_timeout,
                )
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None

    # ---------------------------------------------------------------------------------------- report
    def _fill_report(self, report: DriveReport) -> None:
        loop_stats = self.profiler.as_dict()
        report.parts = loop_stats["parts"]
        report.lateness_ms = loop_stats["loop"]["lateness"] or {}
        report.overrun_ms = loop_stats["loop"]["overrun"] or {}
        report.part_errors = {e.name: e.errors for e in self.parts if e.errors}

    def format_report(self, report: DriveReport) -> str:
        """The profiler table plus the loop summary, as printed at the end of a drive."""
        rows = [
            ("loops", f"{report.loops} in {report.elapsed_s:.3f} s"),
            ("achieved", f"{report.achieved_hz:.3f} Hz of {report.rate_hz:g} Hz"),
            ("overruns", str(report.overruns)),
            ("skipped deadlines", str(report.skipped_deadlines)),
        ]
        if report.part_errors:
            rows.append(("part errors", ", ".join(f"{k}: {v}" for k, v in report.part_errors.items())))
        rows.append(("stopped by", report.stop_reason))
        return self.profiler.table(rows)

    # -------------------------------------------------------------------------------------- start()
    def start(
        self,
        rate_hz: float = 10,
        max_loop_count: int | None = None,
        verbose: bool = False,
        *,
        duration: float | None = None,
        use_uvloop: bool = True,
    ) -> tuple[int, float]:
        """Donkeycar's blocking entry point: drive on a new event loop and return ``(loops, seconds)``.

        Runs on uvloop when it is installed (unless ``use_uvloop=False``). Ctrl-C and SIGTERM stop the car
        cleanly: the current tick finishes, every part is shut down, and the report is logged.
        """
        report = run_blocking(
            self.run_with_signals(rate_hz, max_loop_count, duration=duration, verbose=verbose),
            use_uvloop=use_uvloop,
        )
        return report.loops, report.elapsed_s

    async def run_with_signals(
        self, rate_hz: float = 20, max_loop_count: int | None = None, **kwargs: Any
    ) -> DriveReport:
        """:meth:`run` with SIGINT and SIGTERM bound to :meth:`stop` for the duration (main thread only)."""
        loop = asyncio.get_running_loop()
        installed: list[int] = []
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                    loop.add_signal_handler(sig, self._on_signal, sig)
                    installed.append(sig)
        try:
            return await self.run(rate_hz, max_loop_count, **kwargs)
        finally:
            for sig in installed:
                loop.remove_signal_handler(sig)

    def _on_signal(self, sig: int) -> None:
        logger.info("received %s: stopping", signal.Signals(sig).name)
        self._stop_reason = self._stop_reason or signal.Signals(sig).name
        self.stop()


def run_blocking(coro: Any, *, use_uvloop: bool = True) -> Any:
    """Run ``coro`` to completion on a fresh event loop (uvloop when available and wanted)."""
    factory = None
    if use_uvloop:
        try:
            import uvloop
        except ImportError:  # pragma: no cover - uvloop is a base dependency on Linux/macOS
            uvloop = None
        if uvloop is not None:
            factory = uvloop.new_event_loop
    with asyncio.Runner(loop_factory=factory) as runner:
        return runner.run(coro)


def _set_done(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


def _channel_list(value: Any, arg: str, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        raise PartSpecError(
            f"{where}: {arg} must be a list of channel names, got the string {value!r}; did you mean [{value!r}]?"
        )
    if not isinstance(value, list | tuple):
        raise PartSpecError(f"{where}: {arg} must be a list or tuple of channel names, got {type(value).__name__}")
    for i, v in enumerate(value):
        if not isinstance(v, str) or not v:
            raise PartSpecError(f"{where}: {arg}[{i}] must be a non-empty channel name (str), got {v!r}")
    return tuple(value)


def _check_arity(fn: Callable[..., Any], n: int, where: str, method: str) -> None:
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return
    try:
        sig.bind(*([None] * n))
    except TypeError as exc:
        raise PartSpecError(f"{where}: {method}() cannot take the {n} input(s) given: {exc}") from None
