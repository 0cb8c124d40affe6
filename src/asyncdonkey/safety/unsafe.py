"""How long an actuator's output was unsafe: from the deadline that made it so to the safe state landing.

An *event* opens when a command's deadline passes while the output shows a driving pulse, whoever notices
first (the actuator's writer, the watchdog thread, the tick). It closes when a safe-state write lands, from any
path: the actuator's writer, the watchdog (whose write may take several attempts on a NACKing bus), or the
safety process, whose latest landing the car reads from their shared state. It also closes when a fresh
command makes the question moot. The time is measured from the deadline, not from when anyone noticed, so a
watchdog that was starved of CPU shows up as unsafe time instead of hiding behind its own late start.
"""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["UnsafeTime"]


class UnsafeTime:
    """One actuator's unsafe events, their total and their longest. Callers serialise access (the actuator's
    write lock), since the watchdog thread and the loop thread both report to it."""

    __slots__ = ("events", "guard_last", "max_s", "open_since", "total_s")

    def __init__(self) -> None:
        self.events = 0
        self.total_s = 0.0
        self.max_s = 0.0
        #: the deadline of the event in progress (``None``: the output is safe or driving on a fresh command)
        self.open_since: float | None = None
        #: ``() -> (cause, landed)`` of the safety process's latest safe write for this output, if it has one
        self.guard_last: Callable[[], tuple[float, float]] | None = None

    def stale(self, deadline: float, output_safe: bool) -> None:
        """The command went stale at ``deadline``; the output shows the safe state already or not."""
        if self.open_since is None and not output_safe and math.isfinite(deadline):
            self.open_since = deadline

    def closed(self, t: float) -> None:
        """A safe-state write landed at ``t``, or a fresh command arrived: the event in progress ends then,
        or when the safety process's write for the same deadline landed, if that was earlier."""
        since = self.open_since
        if since is None:
            return
        self.open_since = None
        end = t
        if self.guard_last is not None:
            cause, landed = self.guard_last()
            if cause == since and landed == landed and landed < end:  # landed == landed: not nan
                end = landed
        dt = max(0.0, end - since)
        self.events += 1
        self.total_s += dt
        if dt > self.max_s:
            self.max_s = dt

    def as_dict(self) -> dict[str, float]:
        return {"events": self.events, "total": self.total_s * 1e3, "max": self.max_s * 1e3}
