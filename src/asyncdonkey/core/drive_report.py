"""The report of one drive: what it did, filled by the parts of the runtime that measured it.

It sits below everything that fills it (the drive, the watchdog, the safety process, shutdown) and everything
that carries it (``PartError.report``), so none of them has to import the loop to name it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .profiler import Profiler

__all__ = ["DriveReport", "format_report"]

#: How the summary says why a drive ended, for the reasons the loop sets itself (``DriveReport.stop_reason`` keeps
#: the short names, which code compares against): "stop()" alone read as if someone had called it.
_STOP_WORDS = {
    "max_loop_count": "loop limit reached (max_loop_count)",
    "duration": "time limit reached (duration)",
    "stop()": "stop() called",
}


@dataclass
class DriveReport:
    """What one drive did. Times are seconds on the runtime clock unless the name says ``_ms``.

    Attributes:
        loops: ticks run.
        elapsed_s: from the first tick's deadline to the end of the last tick. Anchored at the deadline, not at
            the first tick's start: a drive whose first ticks came late (a loaded machine at start-up) counts
            that time too, so ``loops + skipped_deadlines`` is the number of deadlines in it.
        achieved_hz: ``(loops - 1) / (last tick start - first tick's deadline)``; ``rate_hz`` when every tick
            starts on its deadline, and never more: tick ``i`` cannot start before deadline ``i``.
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


def format_report(report: DriveReport, profiler: Profiler) -> str:
    """The profiler table plus the loop summary, as printed at the end of a drive (``profiler``: the drive's)."""
    rows = [
        ("loops", f"{report.loops} in {report.elapsed_s:.3f} s"),
        ("achieved", f"{report.achieved_hz:.3f} Hz of {report.rate_hz:g} Hz"),
        ("overruns", str(report.overruns)),
        ("skipped deadlines", str(report.skipped_deadlines)),
    ]
    if report.spin_window_ms is not None:
        sleeps = "two sleeps" if report.precise_sleeps == 2 else "one sleep"
        rows.append(("precise spin window", f"{report.spin_window_ms:.3f} ms (learned; after {sleeps})"))
    for name, lat in report.latency_ms.items():
        rows.append(
            (
                f"sensing-to-actuation ({name})",
                f"p50 {lat['50%']:.1f} ms, p99 {lat['99%']:.1f} ms, max {lat['max']:.1f} ms",
            )
        )
    for name, p in report.pipelined.items():
        rows.append(
            (
                f"pipelined {name}",
                f"{p['runs']} runs at {p['rate_hz']:.2f} Hz (loop {report.achieved_hz:.2f} Hz), "
                f"{p['superseded']} starts superseded while it was busy",
            )
        )
    for name, g in report.reentries_avoided.items():
        if g["waited"] or g["coalesced"]:
            rows.append(
                (
                    f"one call at a time ({name})",
                    f"{g['waited']} calls waited for its running call, {g['coalesced']} served by a newer one",
                )
            )
    for name, push in report.pushed.items():
        if push["superseded"]:
            rows.append((f"pushed {name}", f"{push['superseded']} pushes superseded while their reactions ran"))
    if report.part_errors:
        rows.append(("part errors", ", ".join(f"{k}: {v}" for k, v in report.part_errors.items())))
    if report.watchdog_events:
        failed = report.watchdog_failed_attempts
        retried = f", {failed} failed writes retried" if failed else ""
        rows.append(("watchdog", f"{report.watchdog_events} safe-state events{retried}"))
    for name, u in report.unsafe_ms.items():
        rows.append((f"unsafe ({name})", f"{u['events']} times, {u['total']:.0f} ms in all, longest {u['max']:.0f} ms"))
    sp = report.safety_process
    if sp is not None:
        lost = sp.get("lost", 0)
        lost_row = f"; lost {lost} times ({sp['lost_why'][-1]}), restarted {sp.get('restarts', 0)}" if lost else ""
        rows.append(
            (
                "safety process",
                f"guarded {', '.join(sp['outputs'])}; {sp['events']} safe-state events, "
                f"{sp['failed_attempts']} failed writes retried{lost_row}",
            )
        )
    if report.shutdown_abandoned:
        rows.append(("shutdown abandoned", ", ".join(report.shutdown_abandoned)))
    if report.longest_block_ms is not None:
        ms, part = report.longest_block_ms
        rows.append(("longest loop block", f"{ms:,.0f} ms by part {part!r}"))
    rows.append(("stopped by", _STOP_WORDS.get(report.stop_reason, report.stop_reason)))
    return profiler.table(rows)
