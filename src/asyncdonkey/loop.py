"""The drive loop: :class:`Vehicle` runs parts in order at ``rate_hz`` on monotonic deadlines.

Design notes:

* **Deadlines, not sleeps.** Tick ``k`` is due at ``t0 + k / rate_hz`` on the runtime clock. Donkeycar sleeps
  ``1/rate_hz - elapsed`` from each tick's own start, so every tick's scheduling error accumulates and its
  loop drifts (-0.7 % at 20 Hz, -17 % at 1 kHz). Absolute deadlines cannot drift.
* **No catch-up bursts.** After an overrun the next tick starts at once; when the loop is more than a period
  behind, the missed deadlines are skipped and counted instead of being run back to back.
* **Decided at add().** How a part is called (inline, awaited, offloaded, threaded) is worked out once in
  :meth:`Vehicle.add`; each tick only walks a list of prepared entries.
* **One clock.** All timing comes from :func:`asyncdonkey.clock.get_clock` for the loop ``run()`` runs on, so
  on :class:`asyncdonkey.clock.virtual_loop.VirtualClockLoop` the whole drive is virtual and deterministic.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any

from .clock import get_clock
from .contracts import Contract, Contracts
from .core.buildscope import note_vehicle
from .core.drive import Drive
from .core.drive_report import DriveReport, format_report
from .core.drivestate import DriveSettings
from .core.plan import AGE_SUFFIX, Entry, OnError, PartOptions, build_entry, make_offload
from .core.profiler import Profiler
from .core.signals import stop_on_signals
from .errors import AsyncdonkeyError, OutputCountError, PartError, PartSpecError, PartTimeoutError
from .memory import Memory

__all__ = [
    "AGE_SUFFIX",
    "AsyncdonkeyError",
    "DriveReport",
    "OutputCountError",
    "PartError",
    "PartSpecError",
    "PartTimeoutError",
    "Vehicle",
]

logger = logging.getLogger(__name__)


class Vehicle:
    """Runs parts in order, ``rate_hz`` times a second, passing values through :attr:`mem`.

    Drop-in for Donkeycar's ``Vehicle``: ``add(part, inputs, outputs, threaded, run_condition)`` and
    ``start(rate_hz, max_loop_count, verbose)`` behave as Donkeycar users know them. :meth:`run` is the same
    loop as a coroutine, for embedding in an asyncio application or a test on the virtual clock.

    A Vehicle is the car's *definition*; each :meth:`run` makes a fresh drive (its own profiler, counters,
    stop latch, background tasks and watchdog), so a vehicle can be driven again and each report covers one
    drive. :attr:`profiler` and :attr:`last_report` are those of the current (or latest) drive.
    """

    #: a sync part holding the loop thread longer than this is named in a warning when it returns
    block_report_s = 0.25
    #: with :meth:`run_with_signals` (``asyncdonkey run``, :meth:`start`): how long after SIGINT/SIGTERM/SIGHUP the
    #: car may go without running its signal handler (C code holding the GIL) before its safety process ends it
    exit_grace_s: float = 2.0
    #: checked mode for vehicles that do not say (``checked=None``): off on the car and, unless they ask, in tests;
    #: asyncdonkey's pytest plugin turns it on for a project (``asyncdonkey_checked = true`` in its pytest ini) or a
    #: test (``@pytest.mark.asyncdonkey_checked``)
    checked_by_default: bool = False

    def __init__(
        self,
        mem: Memory | None = None,
        *,
        profiler_window: int | None = None,
        safety_process: bool | None = None,
        contracts: Contracts | Mapping[str, Contract] | None = None,
        checked: bool | None = None,
    ) -> None:
        #: what each channel's values may be (``asyncdonkey.contracts``): the Donkeycar defaults, then whatever is
        #: declared here, with :meth:`declare`, or by a part's ``contracts`` mapping when it is added. Boundary
        #: parts (network and web receivers) check what they admit against these.
        self.contracts = contracts if isinstance(contracts, Contracts) else Contracts(contracts)
        if checked is not None and type(checked) is not bool:
            raise ValueError(f"Vehicle: checked must be True, False or None, got {checked!r}")
        #: checked mode (a test-time aid): every part output is checked against its channel's contract and a
        #: value that breaks it is a ContractViolation naming the part, handled as that part's error (``on_error``)
        #: and never stored. ``None``: :attr:`checked_by_default` when a drive starts; ``run(checked=)`` overrides
        self.checked = checked
        #: the safety process (``asyncdonkey.safety``): ``None`` starts it on a real loop whenever an actuator
        #: has an output it can reach (a PCA9685 channel) and drives on without it, logging why, if it cannot
        #: start; ``True`` requires it (the drive does not start without it); ``False`` never starts it
        self.safety_process = safety_process
        self.mem = mem if mem is not None else Memory()
        self._profiler_window = profiler_window
        self.profiler = self._new_profiler()
        self.parts: list[Entry] = []
        self.last_report: DriveReport | None = None
        self._drive: Drive | None = None
        self._pending_stop: str | None = None
        self._offload = make_offload(self._executor_for_offload)
        #: the exit grace the safety process enforces, while run_with_signals has the signals (else None)
        self._signal_exit_grace: float | None = None
        note_vehicle(self)  # a build() that raises after making it: `asyncdonkey run` shuts its parts down

    @property
    def on(self) -> bool:
        """Whether the drive in progress is ticking (Donkeycar's flag): false before its first tick starts, once its
        ticks have ended (during shutdown too) and between drives."""
        drive = self._drive
        return drive is not None and drive.on

    @property
    def drive(self) -> Drive | None:
        """The drive in progress (``None`` between runs): its live counters ``loops``, ``overruns``,
        ``skipped`` and its ``profiler``, for parts that report on the loop while it runs."""
        return self._drive

    def _new_profiler(self) -> Profiler:
        return Profiler() if self._profiler_window is None else Profiler(self._profiler_window)

    def _executor_for_offload(self) -> Any:
        drive = self._drive
        if drive is None:
            raise RuntimeError("Vehicle: an executor=True part was called outside a drive")
        return drive.work.get_executor()

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
        inputs: Sequence[str | None] = (),
        outputs: Sequence[str] = (),
        threaded: bool = False,
        run_condition: str | None = None,
        *,
        executor: bool = False,
        on_error: OnError = "stop",
        name: str | None = None,
        shutdown_timeout: float = 2.0,
        timeout: float | None = None,
        actuator: bool | None = None,
        pipelined: bool = False,
        trigger: str | None = None,
        react: bool = False,
    ) -> None:
        """Add ``part`` to the end of the drive loop.

        Args:
            part: an object with ``run(*inputs)`` (sync or ``async``), or with ``update()`` plus
                ``run_threaded(*inputs)`` when ``threaded``. An ``async def update(self)`` always runs as a
                background task beside the ticks.
            inputs: channel names read from :attr:`mem` and passed positionally. A name ending in ``@age``
                (``"user/throttle@age"``) passes the age of that channel's value instead: seconds since the
                sensing behind it (``docs/provenance.md``). ``None`` passes ``None``.
            outputs: channel names the returned value is written to. ``None`` writes nothing; one output
                stores the value as is; several unpack it (fewer values is an error; extra values are ignored
                with a warning, as Donkeycar does).
            threaded: Donkeycar's threaded part: a sync ``update()`` loop runs in its own thread and
                ``run_threaded()`` is called each tick.
            run_condition: a channel name; the part runs only on ticks where that channel is truthy.
            executor: run a sync ``run`` in a worker thread, still awaited in order (heavy compute).
            on_error: ``"stop"`` (default) stops the car and raises :class:`PartError` from ``run()``;
                ``"continue"`` logs (rate-limited), counts and carries on.
            name: the name used in reports and errors (default: the part's class name, made unique).
            shutdown_timeout: seconds allowed for this part's ``shutdown()``; passed to a ``shutdown`` that
                takes a ``timeout`` keyword.
            timeout: for an awaited part (async ``run`` or ``executor=True``): seconds after which the call is
                cancelled and handled by ``on_error`` as a :class:`PartTimeoutError`.
            actuator: shut this part down in the first, safe-state phase (default: decided from the part:
                it has ``safe_state_sync``, or it is one of Donkeycar's actuator parts).
            pipelined: run the part beside the ticks instead of inside them: whenever it is free it takes the
                newest inputs, computes (a sync ``run`` in a worker thread) and publishes; the ticks read its
                outputs as latest values (``asyncdonkey.core.pipeline``).
            trigger: for a pipelined part, the input whose new values start it (the camera frame), instead of
                the tick.
            react: also run this part the moment a pipelined part upstream of it publishes (``DriveMode``, the
                actuators), not only in its place in the tick.
        """
        label = name or type(part).__name__
        if self._drive is not None:
            raise PartSpecError(f"Vehicle.add({label}): parts cannot be added while the vehicle is running")
        self._take_contracts(part, label)
        options = PartOptions(
            name=self._unique_name(label),
            inputs=inputs,
            outputs=outputs,
            threaded=threaded,
            run_condition=run_condition,
            executor=executor,
            on_error=on_error,
            shutdown_timeout=shutdown_timeout,
            timeout=timeout,
            actuator=actuator,
            pipelined=pipelined,
            trigger=trigger,
            react=react,
        )
        e = build_entry(self.mem, part, options, self._offload)
        self.profiler.series_for(e.name)  # listed in the profiler from now on, before any drive
        self.parts.append(e)
        logger.debug("added part %s inputs=%s outputs=%s", e.name, e.inputs, e.outputs)

    def declare(self, channel: str, contract: Contract) -> None:
        """Declare what ``channel``'s values may be (see ``docs/contracts.md``); replaces a default."""
        self.contracts.declare(channel, contract)

    def _take_contracts(self, part: Any, label: str) -> None:
        """A part may declare its channels' contracts (a ``contracts`` mapping) and may check what it receives
        against the car's (a ``use_contracts(contracts)`` method, called here with :attr:`contracts`)."""
        declared = getattr(part, "contracts", None)
        if isinstance(declared, Mapping):
            for channel, contract in declared.items():
                if not isinstance(contract, Contract):
                    raise PartSpecError(f"Vehicle.add({label}): contracts[{channel!r}] is not a Contract: {contract!r}")
                self.contracts.declare(channel, contract)
        use = getattr(part, "use_contracts", None)
        if callable(use):
            use(self.contracts)

    def _unique_name(self, label: str) -> str:
        names = {e.name for e in self.parts}
        if label not in names:
            return label
        n = 2
        while f"{label}#{n}" in names:
            n += 1
        return f"{label}#{n}"

    # ------------------------------------------------------------------------------------------ stop()
    def stop(self, reason: str = "stop()") -> None:
        """Ask the drive loop to stop: the current tick finishes, then shutdown runs.

        Safe from any thread and from a signal handler. Called before the drive has started (say right after
        ``asyncio.create_task(v.run())``), it is kept and honoured by the next run.
        """
        drive = self._drive
        if drive is not None:
            drive.request_stop(reason)
        else:
            self._pending_stop = self._pending_stop or reason

    # ------------------------------------------------------------------------------------------- run()
    async def run(
        self,
        rate_hz: float = 20,
        max_loop_count: int | None = None,
        *,
        duration: float | None = None,
        verbose: bool = False,
        report_every: int = 200,
        stop_grace_s: float = 1.0,
        precise: bool = False,
        checked: bool | None = None,
    ) -> DriveReport:
        """Drive until ``max_loop_count`` ticks, ``duration`` seconds, :meth:`stop` or cancellation.

        Installs no signal handlers and never touches the event loop policy, so it can run inside any asyncio
        application. Every ending shuts the car down (actuators to their safe state first) and fills a complete
        :class:`DriveReport`, also kept as :attr:`last_report`. Cancelling the task that awaits it shuts the
        vehicle down before the ``CancelledError`` propagates. Raises :class:`PartError` (with the report as
        ``.report``) when a part with ``on_error="stop"`` fails. After a stop request, an awaited part that has
        not returned within ``stop_grace_s`` is cancelled, so a stop always ends the drive.

        ``precise=True`` spins the last stretch before each deadline (a window learned from the observed
        wake-up latency, see :class:`~asyncdonkey.clock.DeadlineWaiter`): tighter ticks for some CPU.

        ``checked`` turns checked mode on or off for this drive (``None``: the vehicle's :attr:`checked`).
        """
        _check_run_args(rate_hz, max_loop_count, duration, stop_grace_s, checked)
        if self._drive is not None:
            raise RuntimeError("Vehicle.run: this vehicle is already running")
        drive = self._new_drive(float(rate_hz), float(stop_grace_s), bool(precise), checked)
        try:
            return await drive.run(max_loop_count, duration, verbose, report_every)
        finally:
            self.last_report = drive.report
            self._drive = None
            self._pending_stop = None

    def _new_drive(self, rate_hz: float, stop_grace_s: float, precise: bool, checked: bool | None) -> Drive:
        """A fresh drive on the running loop: its clock, profiler, report and stop latch (a stop asked for before
        the run is honoured), checked mode as asked, and the safety process as :attr:`safety_process` asks."""
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        self.mem.use_clock(clock.now)
        report = DriveReport(rate_hz=rate_hz)
        self.profiler = profiler = self._new_profiler()
        settings = DriveSettings(
            stop_grace_s=stop_grace_s,
            block_report_s=self.block_report_s,
            precise=precise,
            want_safety_process=self.safety_process,
            exit_grace_s=self._signal_exit_grace,
        )
        drive = Drive(tuple(self.parts), self.mem, clock, loop, profiler, report, settings)
        self._drive = drive
        if self._checked_for(checked):
            report.checked = True
            report.checked_parts = drive.check_outputs(self.contracts)
        if self._pending_stop is not None:
            drive.stop_latch.requested, drive.stop_latch.reason = True, self._pending_stop
            self._pending_stop = None
        return drive

    def _checked_for(self, checked: bool | None) -> bool:
        """Whether a drive runs checked: the run's say, else the vehicle's, else :attr:`checked_by_default` (read
        when the drive starts, so a test that turns the default off covers vehicles built before it)."""
        if checked is not None:
            return checked
        return self.checked if self.checked is not None else bool(self.checked_by_default)

    # ---------------------------------------------------------------------------------------- report
    def format_report(self, report: DriveReport) -> str:
        """The profiler table plus the loop summary, as printed at the end of a drive."""
        return format_report(report, self.profiler)

    def shutdown_deadline_s(self) -> float:
        """The longest shutdown can take: the safe-state phase, then the slowest of the other parts."""
        actuators = [e.shutdown.timeout for e in self.parts if e.actuator] or [0.0]
        others = [e.shutdown.timeout for e in self.parts if not e.actuator] or [0.0]
        return max(actuators) + max(others) + 1.0

    # -------------------------------------------------------------------------------------- start()
    def start(
        self,
        rate_hz: float = 10,
        max_loop_count: int | None = None,
        verbose: bool = False,
        *,
        duration: float | None = None,
        use_uvloop: bool = True,
        precise: bool = False,
        exit_grace_s: float | None = None,
    ) -> tuple[int, float]:
        """Donkeycar's blocking entry point: drive on a new event loop and return ``(loops, seconds)``.

        Runs on uvloop when it is installed (unless ``use_uvloop=False``). The first Ctrl-C or SIGTERM stops the
        car (the tick finishes, actuators go to their safe state, every part is shut down, the report is
        logged) within a bounded time even if a part hangs; a second one exits at once with status 130. A car
        that cannot run its signal handler (C code holding the GIL) is ended by its safety process
        ``exit_grace_s`` after the signal (:meth:`run_with_signals`).
        """
        report = run_blocking(
            self.run_with_signals(
                rate_hz, max_loop_count, duration=duration, verbose=verbose, precise=precise, exit_grace_s=exit_grace_s
            ),
            use_uvloop=use_uvloop,
        )
        return report.loops, report.elapsed_s

    async def run_with_signals(
        self,
        rate_hz: float = 20,
        max_loop_count: int | None = None,
        *,
        exit_grace_s: float | None = None,
        **kwargs: Any,
    ) -> DriveReport:
        """:meth:`run` with SIGINT, SIGTERM and SIGHUP bound to the two-step stop (``asyncdonkey.core.signals``).

        With a safety process, the signals reach it too, and a car that has not run its signal handler within
        ``exit_grace_s`` (default :attr:`exit_grace_s`, 2 s) of one, or has not ended by the bound its handler set
        (the stop grace plus the shutdown deadline), is ended by it: safe state, one line, SIGKILL."""
        grace = self.exit_grace_s if exit_grace_s is None else exit_grace_s
        if not (isinstance(grace, int | float) and grace > 0):
            raise ValueError(f"Vehicle.run_with_signals: exit_grace_s must be a positive number, got {grace!r}")
        self._signal_exit_grace = float(grace)
        try:
            with stop_on_signals(self, self.shutdown_deadline_s()):
                return await self.run(rate_hz, max_loop_count, **kwargs)
        finally:
            self._signal_exit_grace = None


def _check_run_args(rate_hz: Any, max_loop_count: Any, duration: Any, stop_grace_s: Any, checked: Any) -> None:
    """``Vehicle.run``'s arguments, each refused with a message that names it."""
    if not (isinstance(rate_hz, int | float) and rate_hz > 0 and math.isfinite(rate_hz)):
        raise ValueError(f"Vehicle.run: rate_hz must be a positive number, got {rate_hz!r}")
    if max_loop_count is not None and (not isinstance(max_loop_count, int) or max_loop_count < 0):
        raise ValueError(f"Vehicle.run: max_loop_count must be a non-negative int, got {max_loop_count!r}")
    if duration is not None and not (isinstance(duration, int | float) and duration >= 0):
        raise ValueError(f"Vehicle.run: duration must be a number of seconds >= 0, got {duration!r}")
    if not (isinstance(stop_grace_s, int | float) and stop_grace_s > 0):
        raise ValueError(f"Vehicle.run: stop_grace_s must be a positive number, got {stop_grace_s!r}")
    if checked is not None and type(checked) is not bool:
        raise ValueError(f"Vehicle.run: checked must be True, False or None, got {checked!r}")


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
