"""How long an actuator's output was unsafe: from the deadline that made it so to the safe state landing.

An *event* opens when a command's deadline passes while the output shows a driving pulse, whoever notices
first (the actuator's writer, the watchdog thread, the tick). It closes when a safe-state write lands, from any
path: the actuator's writer, the watchdog (whose write may take several attempts on a NACKing bus), or the
safety process, whose latest landing the car reads from their shared state. It also closes when a fresh
command makes the question moot. The time is measured from the deadline, not from when anyone noticed, so a
watchdog that was starved of CPU shows up as unsafe time instead of hiding behind its own late start.

What the chip held decides, not who noticed last. The safety process publishes, per output, when its safe write
landed for as long as it is tripped: from its trip (a passed deadline, or a stopped heartbeat) until it sees a
fresh command, so no driving pulse from the car can have landed after it (one that did is read back and
overwritten within 100 ms, and the landing moves to the new write). It publishes nothing while its own heartbeat
is stale (a frozen guard's record is not trusted). When the car closes an event, a landing the guard published
that is earlier ends it there, and one from before the deadline (the guard stopped the output on a stopped
heartbeat) makes it count zero. So a car starved, blocked or frozen while its guard stopped the chip reports
the guard's figure, not the length of its own stall. (The guard's deadline is not compared with the car's: the
car recomputes a command's deadline from its age on every tick, and under CPU starvation the two drift apart by
the time between reading the age and applying it, milliseconds or more.)
"""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["UnsafeTime"]


class UnsafeTime:
    """One actuator's unsafe events, their total and their longest. Callers serialise access (the actuator's
    write lock), since the watchdog thread and the loop thread both report to it."""

    __slots__ = ("events", "guard_counted", "guard_last", "max_s", "open_since", "total_s")

    def __init__(self) -> None:
        self.events = 0
        self.total_s = 0.0
        self.max_s = 0.0
        #: the deadline of the event in progress (``None``: the output is safe or driving on a fresh command)
        self.open_since: float | None = None
        #: ``() -> (deadline, landed)`` of the safety process's trip of this output in progress: the deadline in
        #: force when it tripped, and when its safe write landed (nan while it is not holding the output safe)
        self.guard_last: Callable[[], tuple[float, float]] | None = None
        #: the guard's landing that ended an event last (one landing ends one event)
        self.guard_counted = math.nan

    def stale(self, deadline: float, output_safe: bool) -> None:
        """The command went stale at ``deadline``; the output shows the safe state already or not."""
        if self.open_since is None and not output_safe and math.isfinite(deadline):
            self.open_since = deadline

    def closed(self, t: float) -> None:
        """A safe-state write landed at ``t``, or a fresh command arrived: the event in progress ends then,
        or when the safety process's write for the same command landed, if that was earlier."""
        since = self.open_since
        if since is None:
            return
        self.open_since = None
        end = t
        if self.guard_last is not None:
            _deadline, landed = self.guard_last()
            if landed < end:  # nan (the guard is not holding it safe) compares False
                if landed == self.guard_counted:
                    return  # that landing already ended this interval (the car, not knowing, saw it stale again)
                end = self.guard_counted = landed
        dt = max(0.0, end - since)
        self.events += 1
        self.total_s += dt
        if dt > self.max_s:
            self.max_s = dt

    def as_dict(self) -> dict[str, float]:
        return {"events": self.events, "total": self.total_s * 1e3, "max": self.max_s * 1e3}
