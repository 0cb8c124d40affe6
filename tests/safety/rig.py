"""A PCA9685 register model that timestamps every change of the throttle output, and a rig around it."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

THROTTLE_CH = 0
STEERING_CH = 1
NEUTRAL = 370  # THROTTLE_STOPPED_PWM
HALF = 435  # throttle 0.5 with Donkeycar's default calibration


class TimedPCA9685(PCA9685Model):
    """Records ``(time, pulse)`` of channel 0 at the end of every transfer that changed it.

    ``now`` is the time source: ``time.monotonic`` for real-loop tests (the runtime clock there), the loop's
    ``time`` on the virtual clock. Transfers end on the bus worker thread or on the watchdog thread.
    """

    def __init__(self, now: Callable[[], float] = time.monotonic) -> None:
        self.now = now
        self.timeline: list[tuple[float, int]] = []
        self._tl_lock = threading.Lock()
        super().__init__()

    def end(self) -> None:
        super().end()
        p = self.pulse(THROTTLE_CH)
        with self._tl_lock:
            if not self.timeline or self.timeline[-1][1] != p:
                self.timeline.append((self.now(), p))

    def first_time(self, pulse: int, after: float) -> float | None:
        with self._tl_lock:
            return next((t for t, p in self.timeline if t >= after and p == pulse), None)

    def pulse_at(self, t: float) -> int | None:
        with self._tl_lock:
            last = None
            for when, p in self.timeline:
                if when > t:
                    break
                last = p
            return last


class Rig:
    def __init__(self, now: Callable[[], float] = time.monotonic) -> None:
        self.sim = I2CSimulator()
        self.pca = self.sim.attach(TimedPCA9685(now), address=0x40, bus=1)
        self.buses = self.sim.registry(retry_delay_s=0)

    def throttle(self, **kw) -> PWMThrottle:
        kw.setdefault("arm_s", 0)
        return PWMThrottle("PCA9685.1:40.0", buses=self.buses, **kw)

    def steering(self, **kw) -> PWMSteering:
        return PWMSteering("PCA9685.1:40.1", buses=self.buses, **kw)

    def close(self) -> None:
        self.buses.close_all()


class Const:
    """Publishes the same command every tick (a fresh object each time, like a controller would)."""

    def __init__(self, value: float) -> None:
        self.value = value

    def run(self) -> float:
        return float(self.value) + 0.0
