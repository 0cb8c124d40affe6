"""A stale-command stop for actuators that have no failsafe of their own (the simulator, a foreign driver).

``PWMThrottle`` stops the car itself when its command gets old; an actuator without that (``SimCar``, a
Donkeycar part) gets the same rule from this part, placed just before it::

    v.add(StaleCommandStop(max_age_s=0.25), inputs=["throttle", "throttle@age"], outputs=["throttle"])
    v.add(car, inputs=["angle", "throttle"])

A command whose age (the sensing behind it, see ``docs/provenance.md``) reaches ``max_age_s`` is replaced by
``stopped`` (0.0). With a remote pilot the age includes the network, so losing the pilot, its link or its
camera feed stops the car within the window. Unlike ``PWMThrottle``'s watchdog this acts on ticks only: it
cannot help when the loop itself is stalled.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from ..clock import get_clock
from ..ratelimit import LogThrottle

__all__ = ["StaleCommandStop"]

logger = logging.getLogger(__name__)


class StaleCommandStop:
    """``run(command, age) -> command``, or ``stopped`` once ``age >= max_age_s`` (``None`` age: never written).

    An event (counted in ``events``, logged rate-limited) is a stale command that would have moved the car being
    held back. A stale command that already is ``stopped`` (a controller that has sent nothing but neutral since
    start-up, before anyone connected) is passed on as it is and is no event: nothing was stopped, and a warning
    at every start-up would teach users to ignore the one that matters.
    """

    def __init__(self, max_age_s: float = 0.25, *, stopped: float = 0.0, name: str = "throttle") -> None:
        if not (isinstance(max_age_s, int | float) and max_age_s > 0 and math.isfinite(max_age_s)):
            raise ValueError(f"StaleCommandStop: max_age_s must be a positive number, got {max_age_s!r}")
        self.max_age_s = float(max_age_s)
        self.stopped = stopped
        self.name = name
        self.active = False  # a stale command that would move the car is being held back
        self.events = 0
        self._log = LogThrottle(1.0)

    def run(self, command: Any, age: float | None) -> Any:
        stale = age is None or not age < self.max_age_s
        holding = stale and command is not None and command != self.stopped
        if holding != self.active:
            self.active = holding
            if holding:
                self.events += 1
                now = get_clock().now()
                if self._log.allow("stale", now):
                    logger.warning(
                        "StaleCommandStop: %s command is %.0f ms old (limit %.0f ms): holding %r (event %d)",
                        self.name,
                        math.inf if age is None else age * 1e3,
                        self.max_age_s * 1e3,
                        self.stopped,
                        self.events,
                    )
        if command is None:
            return None
        return self.stopped if stale else command
