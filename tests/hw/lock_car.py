"""A car for the device-lock tests: ``asyncdonkey run lock_car.py -- ENDPOINT``.

It drives the PCA9685 register model that the test process serves (``I2CSimulator.serve``) at ENDPOINT: the
throttle on channel 0 at 0.5 (pulse 435), the steering on channel 1 at 0.5 (pulse 332), no arming pause. It
prints ``driving`` once both pulses are on the chip, then drives until it is stopped or killed (at most 60 s).
"""

from __future__ import annotations

import sys

from asyncdonkey import Vehicle
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.testing.i2c_models import RemoteI2CSimulator

DRIVE_LOOP_HZ = 20


class Pilot:
    def run(self) -> tuple[float, float]:
        return 0.5, 0.5


class Announce:
    """Says ``driving`` once, on the first tick after both commands are on the chip."""

    def __init__(self, steering: PWMSteering, throttle: PWMThrottle) -> None:
        self.steering, self.throttle, self.said = steering, throttle, False

    def run(self) -> None:
        if not self.said and self.throttle.written_pulse == 435 and self.steering.written_pulse == 332:
            self.said = True
            sys.stdout.write("driving\n")
            sys.stdout.flush()


def build(args: list[str]) -> Vehicle:
    buses = RemoteI2CSimulator(args[0]).registry()
    steering = PWMSteering("PCA9685.1:40.1", buses=buses)
    throttle = PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0.0)
    v = Vehicle()
    v.add(Pilot(), outputs=["angle", "throttle"])
    v.add(steering, inputs=["angle"], name="steering")
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    v.add(Announce(steering, throttle))
    return v
