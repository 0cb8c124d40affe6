"""The report of one drive: what it did, filled by the parts of the runtime that measured it.

It sits below everything that fills it (the drive, the watchdog, the safety process, shutdown) and everything
that carries it (``PartError.report``), so none of them has to import the loop to name it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["DriveReport"]


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
        latency_ms: per actuator, percentiles of sensing-to-actuation latency: the time its command reached
            the output minus the origin of the sensing behind that command.
        parts: per-part timing summaries in ms (Donkeycar's columns), by part name.
        part_errors: errors caught and survived under ``on_error="continue"``, by part name.
        watchdog_events: times the watchdog put an actuator in its safe state.
        watchdog_failed_attempts: the watchdog's safe-state writes that failed and were tried again.
        unsafe_ms: per actuator that had any, ``events`` (a command deadline passed while the output showed a
            driving pulse), ``total`` and ``max``: ms from the deadline until the safe state landed on the
            output, by whichever path landed it first (its writer, the watchdog, the safety process).
        safety_process: what the safety process did (``outputs`` it guarded, ``events``, ``failed_attempts``,
            ``heartbeat_timeout_ms``, and per output where it acted), or ``None`` when none ran.
        longest_block_ms: ``(ms, part)`` of the longest time a sync part held the loop thread past
            ``block_report_s``, or ``None``.
        shutdown_abandoned: parts whose ``shutdown()`` (or ``update()`` thread) outlived its timeout and
            was left running on a daemon thread.
        pipelined: per pipelined part, ``runs``, ``published``, its own ``rate_hz`` and ``superseded`` (start
            requests replaced by a newer one while it was busy: frames it never saw).
        reentries_avoided: per part that more than one path can be inside at once (see
            :mod:`asyncdonkey.core.pipeline`: a ``react=True`` part that awaits, an executor part with a timeout), the
            calls that found it still running: ``waited`` (waited for that call to end, then ran it with the inputs
            as they were then) and ``coalesced`` (another call was already waiting: served by that one's run, on
            inputs at least as new; newest wins). A part is never entered twice at once.
        pushed: per push source feeding ``react=True`` parts, ``reactions`` (runs of those parts) and
            ``superseded`` (pushes replaced by a newer one while the reactions to an earlier one still ran).
        stop_reason: ``"max_loop_count"``, ``"duration"``, ``"stop()"``, ``"cancelled"``, ``"error"`` or the
            name of the signal that stopped the car.
        spin_window_ms: in precise mode, the spin window at the end of the drive (learned from the machine's
            wake-up lateness: what each tick spun at most), else ``None``. Precise mode's CPU is mostly this.
        precise_sleeps: in precise mode, how many times each tick slept before its spin at the end of the drive
            (2 where the machine's wake-ups have a long tail, else 1), else ``None``.
        checked: whether the drive ran in checked mode (every part output checked against its channel's
            contract); ``checked_parts``: how many parts had an output with a contract to check.
    """

    loops: int = 0
    elapsed_s: float = 0.0
    achieved_hz: float = 0.0
    rate_hz: float = 0.0
    overruns: int = 0
    skipped_deadlines: int = 0
    lateness_ms: dict[str, float] = field(default_factory=dict)
    overrun_ms: dict[str, float] = field(default_factory=dict)
    latency_ms: dict[str, dict[str, float]] = field(default_factory=dict)
    parts: dict[str, dict[str, float] | None] = field(default_factory=dict)
    part_errors: dict[str, int] = field(default_factory=dict)
    watchdog_events: int = 0
    watchdog_failed_attempts: int = 0
    unsafe_ms: dict[str, dict[str, float]] = field(default_factory=dict)
    safety_process: dict[str, Any] | None = None
    longest_block_ms: tuple[float, str] | None = None
    shutdown_abandoned: list[str] = field(default_factory=list)
    pipelined: dict[str, dict[str, float]] = field(default_factory=dict)
    reentries_avoided: dict[str, dict[str, int]] = field(default_factory=dict)
    pushed: dict[str, dict[str, int]] = field(default_factory=dict)
    stop_reason: str = ""
    spin_window_ms: float | None = None
    precise_sleeps: int | None = None
    checked: bool = False
    checked_parts: int = 0

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)
