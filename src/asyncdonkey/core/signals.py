"""Ctrl-C, SIGTERM and SIGHUP on a car: the first stops the drive within a bounded time, the second exits at once.

Why not ``loop.add_signal_handler``: asyncio runs such a handler from the event loop, so while a sync part
holds the loop thread (a hung camera read, a ``time.sleep``) the handler does not run, and neither Ctrl-C nor
a second Ctrl-C does anything until the part returns. A handler installed with ``signal.signal`` runs in the
main thread between two bytecodes, even inside that part. So:

1. **First signal**: the drive is asked to stop (the tick finishes, shutdown runs, the report prints). An
   awaited part that does not return within the drive's ``stop_grace_s`` is cancelled; a sync part that still
   holds the loop thread after that grace is interrupted with :class:`PartInterrupted` (raised in the part,
   like Ctrl-C would be). If the whole drive has not ended within the grace plus the shutdown deadline, the
   process puts every actuator in its safe state and exits with status 130.
2. **Second signal**: every actuator is put in its safe state from the signal handler, and the process exits
   at once with status 130 (the shell's "terminated by Ctrl-C"), whatever is still running.

SIGHUP (the terminal or SSH session that started the car went away) is a stop like SIGTERM: the drive ends
with its report, instead of the process dying on the spot with the throttle left to the safety process.

All of this needs the main thread to run Python. While C code holds the GIL (a catastrophic regular expression,
a native call that never releases it) no Python handler runs, not even the second one. The safety process covers
that: the interpreter's wakeup descriptor is a pipe it reads (:meth:`SafetyProcess.watch_signals`), so it sees
the signal from the C-level handler at once, and the first handler to run publishes the time by which the drive
will have ended (the stop grace plus the shutdown deadline, plus ``EXIT_MARGIN_S``). A car that has not run its
handler within its exit grace (``Vehicle.exit_grace_s``, 2 s) of the signal, or not ended by the time it
published, is ended by the safety process: every output safe, one line saying why, SIGKILL.

Only the command line and :meth:`Vehicle.start` / :meth:`Vehicle.run_with_signals` install this; a drive
embedded in someone's asyncio application with :meth:`Vehicle.run` leaves signals to the application.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from ..errors import PartInterrupted

if TYPE_CHECKING:
    from ..safety.activity import LoopActivity, RunningCall
    from .runtypes import Stoppable

__all__ = ["EXIT_INTERRUPTED", "PartInterrupted", "force_safe_exit", "stop_on_signals"]

logger = logging.getLogger("asyncdonkey.loop")

EXIT_INTERRUPTED = 130
#: the signals that stop a drive
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: beyond the drive's own bound (stop grace + shutdown deadline), before the safety process ends the car
EXIT_MARGIN_S = 1.0


def force_safe_exit(drive: LoopActivity | None, status: int = EXIT_INTERRUPTED, why: str = "") -> None:
    """Put every actuator of ``drive`` in its safe state, flush the logs and exit the process now."""
    if drive is not None:
        for e in drive.entries:
            fn = getattr(e.part, "safe_state_sync", None)
            if e.actuator and callable(fn):
                try:
                    fn()
                except Exception as exc:  # keep going: the other actuators still matter
                    logger.error("part %r: safe state failed while exiting: %r", e.name, exc)
    logger.error("exiting with status %d%s", status, f": {why}" if why else "")
    for h in logging.getLogger().handlers:
        try:
            h.flush()
        except Exception:
            pass
    sys.stderr.flush()
    os._exit(status)


class _SignalStop:
    def __init__(self, vehicle: Stoppable, shutdown_deadline_s: float) -> None:
        self.vehicle = vehicle
        self.shutdown_deadline_s = shutdown_deadline_s
        self.count = 0
        self._interrupt: tuple[RunningCall, float] | None = None  # (entry, part_started) to interrupt
        self._done = threading.Event()
        self._main_ident = threading.main_thread().ident

    def handler(self, signum: int, frame: Any) -> None:
        drive = self.vehicle.drive
        pending = self._interrupt
        if pending is not None and drive is not None and drive.current is pending[0]:
            # our own re-delivery after the grace: interrupt the sync part that still holds the loop thread
            self._interrupt = None
            if drive.part_started == pending[1]:
                raise PartInterrupted(
                    f"part {pending[0].name!r} interrupted: it held the loop thread "
                    f"{time.monotonic() - pending[1]:.1f} s and did not return within the stop grace"
                )
            return
        self.count += 1
        name = signal.Signals(signum).name
        if self.count > 1:
            force_safe_exit(drive, EXIT_INTERRUPTED, f"second {name}")
        safety = getattr(drive, "safety_process", None)
        if safety is not None:  # the safety process ends the car if it has not ended by then
            grace = drive.stop_grace_s if drive is not None else 1.0
            safety.exit_requested(time.monotonic() + grace + self.shutdown_deadline_s + EXIT_MARGIN_S)
        logger.info("received %s: stopping (again to exit at once)", name)
        self.vehicle.stop(name)
        threading.Thread(target=self._enforce, args=(drive,), name="asyncdonkey-stop", daemon=True).start()

    def _enforce(self, drive: LoopActivity | None) -> None:
        """After the grace, interrupt a sync part still holding the loop; after the deadline, exit."""
        grace = drive.stop_grace_s if drive is not None else 1.0
        if self._done.wait(grace):
            return
        if drive is not None:
            e = drive.current
            if e is not None and e.is_sync_inline and self._main_ident is not None:
                self._interrupt = (e, drive.part_started)
                signal.pthread_kill(self._main_ident, signal.SIGINT)
        if self._done.wait(self.shutdown_deadline_s):
            return
        force_safe_exit(
            drive, EXIT_INTERRUPTED, f"the drive did not end within {grace + self.shutdown_deadline_s:.1f} s"
        )

    def finished(self) -> None:
        self._done.set()


@contextmanager
def stop_on_signals(vehicle: Stoppable, shutdown_deadline_s: float) -> Iterator[None]:
    """Bind SIGINT, SIGTERM and SIGHUP to the two-step stop for the duration (main thread only; else does nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    stopper = _SignalStop(vehicle, shutdown_deadline_s)
    previous = {}
    for sig in STOP_SIGNALS:
        try:
            previous[sig] = signal.signal(sig, stopper.handler)
        except (ValueError, OSError):  # not the main interpreter, or the platform refuses
            pass
    try:
        yield
    finally:
        stopper.finished()
        for sig, old in previous.items():
            signal.signal(sig, old)
