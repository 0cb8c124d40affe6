"""The watchdog: actuators reach their safe state when their command goes stale, whatever the loop does.

Why a thread. The stale-command failsafe used to be a timer on the event loop. A sync part that blocks the loop
thread (a camera read, a model run inline, a ``time.sleep`` in someone's part) blocks that timer too, and the
car keeps driving on its last command for as long as the block lasts. The watchdog is a plain thread: it reads
each actuator's command deadline (the origin of the sensing behind its command plus the failsafe window, on the
monotonic clock, which any thread can read) and, when one passes, writes the safe state through the actuator's
own synchronous path (``safe_state_sync``), which takes the bus lock only for the transfer. A Python loop that
holds the GIL still lets it run: the interpreter switches threads every ``sys.getswitchinterval()`` (5 ms).

It sleeps until the earliest deadline (an actuator pokes it when a deadline moves earlier), so it costs a
wake-up per failsafe window at most, not a poll.

A safe-state write that fails (the bus NACKs past its own retries, a transfer times out) is retried until it
lands, with a backoff from 2 ms doubling to at most 50 ms, each attempt counted (``failed_attempts``) and
logged at most once a second. Giving up would leave the car driving on its last pulse for as long as the
stall lasts; only a fresh command (the output's own writer takes over) or the end of the drive ends the
retries. The time the output stayed unsafe is measured from the deadline (:mod:`asyncdonkey.safety.unsafe`).

It also watches the safety process (when the drive has one): every ``CHECK_S`` it calls the guard's
:meth:`~asyncdonkey.safety.process.SafetyProcess.check`, which notices a guard that has exited or frozen and
answers it (the throttle to its safe state from this thread, a new guard). The event loop has no part in it, so a
blocked loop does not hide a lost guard.

What it cannot do: it lives in the car's process. C code that holds the GIL freezes it with the rest, enough
busy Python threads can starve it past its window, and a process killed with SIGKILL runs no code at all, while
a PCA9685 keeps outputting its last pulse. The safety process (:mod:`asyncdonkey.safety.guard`) covers those.

On the virtual clock there is no watchdog thread: virtual time does not pass while the loop thread is busy, so
a command cannot go stale during a block, and the actuators' own in-loop timers cover every other case exactly.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ..ratelimit import LogThrottle

if TYPE_CHECKING:
    from ..core.plan import Entry
    from .activity import LoopActivity

__all__ = ["ActuatorRuntime", "Watchdog"]

logger = logging.getLogger("asyncdonkey.watchdog")  # the name its log lines have always had

#: The longest the watchdog sleeps without a deadline to wait for (it is poked when one appears).
_IDLE_WAKE_S = 1.0
#: A failed safe-state write is tried again after this, doubling each time up to the cap.
RETRY_FIRST_S = 0.002
RETRY_MAX_S = 0.05


class ActuatorRuntime:
    """What an actuator gets from the drive it is part of (``Actuator.attach``)."""

    __slots__ = ("_guard_set", "_watchdog", "guard_last", "record_latency")

    def __init__(
        self,
        record_latency: Callable[[float, float], None],
        watchdog: Watchdog | None,
        guard_set: Callable[[float], None] | None = None,
        guard_last: Callable[[], tuple[float, float]] | None = None,
    ) -> None:
        #: call with (time the command reached the output, origin of the command); once per command
        self.record_latency = record_latency
        self._watchdog = watchdog
        #: publishes the command deadline to the safety process (``None``: none guards this actuator)
        self._guard_set = guard_set
        #: ``(cause, landed)`` of the safety process's latest safe write for this actuator
        self.guard_last = guard_last

    def deadline_changed(self, deadline: float) -> None:
        """A command was applied with this deadline: tell the safety process, and the watchdog if it moved
        earlier than the watchdog's next wake-up."""
        gs = self._guard_set
        if gs is not None:
            gs(deadline)
        wd = self._watchdog
        if wd is not None and deadline < wd.next_wake:
            wd.poke()


class _Trip:
    """The watchdog's state for one actuator: tripped, the safe write still to land, its attempts."""

    __slots__ = ("attempts", "deadline", "next_attempt", "pending", "tripped")

    def __init__(self) -> None:
        self.tripped = False
        self.pending = False
        self.deadline = math.inf
        self.attempts = 0
        self.next_attempt = 0.0


class Watchdog:
    """One thread per drive on a real loop, watching every actuator that has a command deadline."""

    def __init__(self, drive: LoopActivity, actuators: list[Entry], now: Callable[[], float] = time.monotonic) -> None:
        self.drive = drive
        self.actuators = actuators
        self.now = now
        self.events = 0
        #: safe-state writes that failed and were tried again
        self.failed_attempts = 0
        self.next_wake = math.inf
        self._trips: dict[str, _Trip] = {e.name: _Trip() for e in actuators}
        self._log = LogThrottle(1.0)
        self._event = threading.Event()
        self._stopped = False
        self._thread: threading.Thread | None = None
        #: ``check(now) -> when to call again``: the safety process's liveness check (``None``: no guard)
        self.monitor: Callable[[float], float] | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name="asyncdonkey-watchdog", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopped = True
        self._event.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(1.0)

    def poke(self) -> None:
        self._event.set()

    def _main(self) -> None:
        while not self._stopped:
            now = self.now()
            wake = now + _IDLE_WAKE_S
            for e in self.actuators:
                try:
                    deadline = e.part.command_deadline()
                except Exception as exc:  # an actuator bug must not kill the watchdog
                    logger.error("watchdog: %r.command_deadline() raised %r", e.name, exc)
                    continue
                trip = self._trips[e.name]
                if deadline <= now:
                    if not trip.tripped:
                        trip.tripped = trip.pending = True
                        trip.deadline, trip.attempts, trip.next_attempt = deadline, 0, now
                        self.events += 1
                    if trip.pending and now >= trip.next_attempt:
                        self._attempt(e, trip, now)
                    if trip.pending and trip.next_attempt < wake:
                        wake = trip.next_attempt
                else:
                    trip.tripped = trip.pending = False  # a fresh command: the output's own writer takes over
                    if deadline < wake:
                        wake = deadline
            wake = min(wake, self._check_guard(now))
            self.next_wake = wake
            self._event.clear()
            if self._stopped:
                break
            self._event.wait(max(0.0, wake - self.now()))
        self.next_wake = math.inf

    def _check_guard(self, now: float) -> float:
        monitor = self.monitor
        if monitor is None:
            return math.inf
        try:
            return monitor(now)
        except Exception as exc:  # a bug there must not kill the watchdog
            logger.error("watchdog: checking the safety process raised %r", exc)
            return now + _IDLE_WAKE_S

    def _attempt(self, e: Entry, trip: _Trip, now: float) -> None:
        """One try at the safe state; on failure the next is scheduled (backoff), never given up."""
        trip.attempts += 1
        try:
            e.part.safe_state_sync()
        except Exception as exc:
            self.failed_attempts += 1
            trip.next_attempt = self.now() + min(RETRY_FIRST_S * 2 ** (trip.attempts - 1), RETRY_MAX_S)
            more = self._log.ready(f"fail:{e.name}", now)
            if more is not None:
                logger.error(
                    "watchdog: %r could not be put in its safe state (attempt %d, %.0f ms after its deadline); "
                    "retrying until it lands: %r%s",
                    e.name,
                    trip.attempts,
                    (now - trip.deadline) * 1e3,
                    exc,
                    more,
                )
            return
        trip.pending = False
        self._landed(e, trip, now)

    def _landed(self, e: Entry, trip: _Trip, now: float) -> None:
        deadline = trip.deadline
        channel = next((i for i in e.inputs if i is not None), "its command")
        window = getattr(e.part, "failsafe_age_s", None)
        drive = self.drive
        blocker = drive.current
        blocked = now - drive.part_started
        where = ""
        if blocker is not None and blocker.is_sync_inline and window is not None and blocked >= window:
            where = f"; the loop has been blocked {blocked * 1e3:,.0f} ms by part {blocker.name!r}"
        late = f" ({(now - deadline) * 1e3:.0f} ms after its deadline)" if now - deadline > 0.01 else ""
        tries = f" after {trip.attempts} attempts" if trip.attempts > 1 else ""
        logger.warning(
            "watchdog: %r: command on %r is stale (failsafe window %s): safe state written%s%s%s (event %d)",
            e.name,
            channel,
            "?" if window is None else f"{window * 1e3:.0f} ms",
            tries,
            late,
            where,
            self.events,
        )


def watched(entries: Any) -> list[Entry]:
    """The actuator entries the watchdog can act on: those with ``command_deadline`` and ``safe_state_sync``."""
    return [
        e
        for e in entries
        if e.actuator
        and callable(getattr(e.part, "command_deadline", None))
        and callable(getattr(e.part, "safe_state_sync", None))
    ]
