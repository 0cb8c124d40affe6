"""The deadline rule every periodic task follows: tick ``k`` is due at ``t0 + k / rate_hz``, skip and count.

Part of the clock (:mod:`asyncdonkey.clock` re-exports it); see docs/timing.md, "The schedule".
"""

from __future__ import annotations

import math

__all__ = ["TICK_EPS", "TIME_EPS", "Schedule"]

#: Float noise in time arithmetic (0.4 + 0.2 = 0.6000000000000001) is neither an overrun nor "behind".
TIME_EPS = 1e-9
#: In periods: a deadline this close to ``now`` counts as passed when working out how far behind a tick is.
TICK_EPS = 1e-6


class Schedule:
    """Deadlines ``t0 + k / rate_hz`` with skip-and-count, the rule every periodic task here follows.

    Computing each deadline from ``t0`` (never by adding periods) means no drift. :meth:`advance` is called
    once a tick's work has ended: when the next deadline has already passed by less than a period, the next
    tick starts at once (it is late, not skipped); when the tick ended more than a period after the next
    deadline, the deadlines it overran are skipped and counted in :attr:`skipped`, and the schedule resumes at
    the latest deadline already passed. A backlog is never run back to back (no burst).
    """

    __slots__ = ("deadline", "k", "period", "rate_hz", "skipped", "t0")

    def __init__(self, rate_hz: float, t0: float) -> None:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"Schedule: rate_hz must be a positive finite number, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.t0 = t0
        #: Number of the current tick (:meth:`advance` moves it, and :attr:`deadline` with it).
        self.k = 0
        #: When the current tick (number :attr:`k`) is due: ``t0 + k / rate_hz``. A plain attribute that
        #: :meth:`advance` keeps up to date (a hot loop reads it once per tick; a property would cost a call).
        self.deadline = t0 + self.k / self.rate_hz
        self.skipped = 0

    def advance(self, end: float) -> int:
        """The current tick's work ended at ``end``: move to the next deadline. Returns the deadlines skipped."""
        rate = self.rate_hz
        t0 = self.t0
        k = self.k + 1
        deadline = t0 + k / rate
        if end - deadline > self.period + TIME_EPS:
            behind = math.floor((end - t0) * rate + TICK_EPS)
            missed = behind - k
            self.skipped += missed
            self.k = behind
            self.deadline = t0 + behind / rate
            return missed
        self.k = k
        self.deadline = deadline
        return 0
