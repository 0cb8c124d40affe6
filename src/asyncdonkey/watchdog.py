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

What it cannot do: a process killed with SIGKILL runs no code at all, and a PCA9685 keeps outputting its last
pulse when the host dies (``docs/safety.md``).

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

if TYPE_CHECKING:
    from .drive import Drive
    from .plan import Entry

__all__ = ["ActuatorRuntime", "Watchdog"]

logger = logging.getLogger("asyncdonkey.watchdog")

#: The longest the watchdog sleeps without a deadline to wait for (it is poked when one appears).
_IDLE_WAKE_S = 1.0


class ActuatorRuntime:
    """What an actuator gets from the drive it is part of (``Actuator.attach``)."""

    __slots__ = ("_watchdog", "record_latency")

    def __init__(self, record_latency: Callable[[float, float], None], watchdog: Watchdog | None) -> None:
        #: call with (time the command reached the output, origin of the command); once per command
        self.record_latency = record_latency
        self._watchdog = watchdog

    def deadline_changed(self, deadline: float) -> None:
        """Tell the watchdog that this actuator's command deadline moved (cheap unless it moved earlier)."""
        wd = self._watchdog
        if wd is not None and deadline < wd.next_wake:
            wd.poke()


class Watchdog:
    """One thread per drive on a real loop, watching every actuator that has a command deadline."""

    def __init__(self, drive: Drive, actuators: list[Entry], now: Callable[[], float] = time.monotonic) -> None:
        self.drive = drive
        self.actuators = actuators
        self.now = now
        self.events = 0
        self.next_wake = math.inf
        self._tripped: dict[str, bool] = {e.name: False for e in actuators}
        self._event = threading.Event()
        self._stopped = False
        self._thread: threading.Thread | None = None

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
                if deadline <= now:
                    if not self._tripped[e.name]:
                        self._trip(e, deadline, now)
                else:
                    self._tripped[e.name] = False
                    if deadline < wake:
                        wake = deadline
            self.next_wake = wake
            self._event.clear()
            if self._stopped:
                break
            self._event.wait(max(0.0, wake - self.now()))
        self.next_wake = math.inf

    def _trip(self, e: Entry, deadline: float, now: float) -> None:
        self._tripped[e.name] = True
        self.events += 1
        try:
            e.part.safe_state_sync()
        except Exception as exc:
            logger.error("watchdog: %r could not be put in its safe state: %r", e.name, exc)
            return
        channel = next((i for i in e.inputs if i is not None), "its command")
        window = getattr(e.part, "failsafe_age_s", None)
        drive = self.drive
        blocker = drive.current
        blocked = now - drive.part_started
        where = ""
        if blocker is not None and blocker.is_sync_inline and window is not None and blocked >= window:
            where = f"; the loop has been blocked {blocked * 1e3:,.0f} ms by part {blocker.name!r}"
        late = f" ({(now - deadline) * 1e3:.0f} ms after its deadline)" if now - deadline > 0.01 else ""
        logger.warning(
            "watchdog: %r: command on %r is stale (failsafe window %s): safe state written%s%s (event %d)",
            e.name,
            channel,
            "?" if window is None else f"{window * 1e3:.0f} ms",
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
