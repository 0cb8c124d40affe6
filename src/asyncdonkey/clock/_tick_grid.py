"""A drive's tick grid, made known to its parts' background work so that their schedules fall on its ticks.

Part of the clock (:mod:`asyncdonkey.clock` re-exports it); see docs/timing.md, "On the drive's tick grid", for
why a background schedule phase-locks to the ticks and what that was measured to save.
"""

from __future__ import annotations

import contextvars
import math
from typing import NamedTuple

from ._schedule import TICK_EPS

__all__ = ["TICK_GRID", "TickGrid", "grid_start", "tick_grid"]


class TickGrid(NamedTuple):
    """A drive's deadlines: ``origin + k * period`` on the runtime clock (``origin`` is its first tick's).

    ``spin_s``: how long before each deadline the drive's thread may spin (precise mode; 0 otherwise), holding
    the interpreter: a read in another thread that is due inside it is published only after the tick.
    """

    origin: float
    period: float
    spin_s: float = 0.0


#: The grid of the drive whose background work this is: set by the drive around the creation of its parts'
#: ``update()`` tasks, which copy it with the rest of their context (so two drives on one loop each have
#: their own, and code outside a drive sees None). Read it with :func:`tick_grid`.
TICK_GRID: contextvars.ContextVar[TickGrid | None] = contextvars.ContextVar("asyncdonkey_tick_grid", default=None)


def tick_grid() -> TickGrid | None:
    """The tick grid of the drive this code runs under (in a part's ``update()`` task), or None."""
    return TICK_GRID.get()


def grid_start(grid: TickGrid | None, rate_hz: float, now: float, lead_s: float = 0.0) -> float:
    """The first deadline of a schedule of ``rate_hz`` started at ``now``: on ``grid`` (a drive's ticks, see
    :func:`tick_grid`), ``lead_s`` before it, at the first such point not before ``now``; without a grid,
    ``now`` itself.

    Phase-locked to the ticks, a background schedule whose period divides the drive's (or is a multiple of it)
    has deadlines that fall on tick deadlines, and the machine wakes once for both instead of twice (less CPU,
    docs/timing.md has the figures). The lead also has a quick read published before the tick that shares its
    deadline, instead of racing it: the tick gets a sample a fraction of a millisecond old.
    """
    if grid is None:
        return now
    period = 1.0 / rate_hz
    origin = grid.origin - lead_s
    return origin + math.ceil((now - origin) / period - TICK_EPS) * period
