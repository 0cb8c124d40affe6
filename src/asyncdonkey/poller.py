"""Hardware pollers: a blocking read called at its own rate off the event loop thread.

An IMU read over I2C or a camera grab blocks for milliseconds; doing it inside the tick (as Donkeycar's
non-threaded parts do) delays every part after it. A :class:`Poller` calls the read in an executor on its own
deadline schedule and publishes each result into a :class:`~asyncdonkey.latest.Latest` cell. The tick reads
the newest value without waiting and can see how old it is.

Add a poller to a vehicle like any part: its ``async update()`` runs as a background task and ``run()``
returns the newest value (``None`` until the first read succeeds)::

    imu = Poller(mpu.read, rate_hz=60, name="imu")
    vehicle.add(imu, outputs=["imu/sample"])
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
from collections.abc import Callable
from typing import Generic, TypeVar

from .clock import get_clock
from .latest import Latest, Sample
from .ratelimit import LogThrottle

__all__ = ["Poller"]

logger = logging.getLogger(__name__)
T = TypeVar("T")


class Poller(Generic[T]):
    """Calls ``read()`` ``rate_hz`` times a second in a worker thread and keeps the newest result.

    * Deadline-based like the drive loop (no drift); a read longer than a period makes the next one start at
      once, and missed deadlines are skipped (``.skipped``), never burst.
    * A read that raises is counted in ``.errors`` and logged at most once per second; polling goes on.
    * Each poller owns one worker thread, so a slow device cannot starve other executor users.
    """

    def __init__(self, read: Callable[[], T], rate_hz: float, name: str | None = None) -> None:
        if not callable(read):
            raise TypeError(f"Poller: read must be callable, got {read!r}")
        if not rate_hz > 0:
            raise ValueError(f"Poller({name or read!r}): rate_hz must be positive, got {rate_hz!r}")
        self.read = read
        self.rate_hz = float(rate_hz)
        self.name = name or getattr(read, "__qualname__", "poller")
        self.latest: Latest[T] = Latest()
        self.reads = 0
        self.errors = 0
        self.skipped = 0
        self.last_error: BaseException | None = None
        self._origin: float | None = None
        self._running = False
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._log = LogThrottle(1.0)

    @property
    def sample(self) -> Sample[T] | None:
        return self.latest.sample

    def run(self) -> T | None:
        s = self.latest.sample
        if s is None:
            return None
        self._origin = s.timestamp
        return s.value

    def output_origin(self) -> float | None:
        """When the value ``run()`` returned was read: re-publishing it on later ticks does not make it young."""
        return self._origin

    async def update(self) -> None:
        loop = asyncio.get_running_loop()
        clock = get_clock(loop)
        now = clock.now
        self._running = True
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"poll:{self.name}")
        period = 1.0 / self.rate_hz
        t0 = now()
        k = 0
        try:
            while self._running:
                deadline = t0 + k / self.rate_hz
                if now() < deadline:
                    await clock.sleep_until(deadline)
                if not self._running:
                    break
                try:
                    value = await loop.run_in_executor(self._executor, self.read)
                except Exception as exc:
                    self.errors += 1
                    self.last_error = exc
                    t = now()
                    if self._log.allow("read", t):
                        held = self._log.take_suppressed("read")
                        logger.warning(
                            "poller %r: read failed (%d errors so far%s): %r",
                            self.name,
                            self.errors,
                            f", {held} not logged" if held else "",
                            exc,
                        )
                else:
                    self.latest.publish(value, now())
                    self.reads += 1
                k += 1
                end = now()
                if end - (t0 + k / self.rate_hz) > period:
                    behind = int((end - t0) * self.rate_hz)
                    self.skipped += behind - k
                    k = behind
        finally:
            self._running = False
            self._executor.shutdown(wait=False, cancel_futures=True)

    def shutdown(self) -> None:
        self._running = False
