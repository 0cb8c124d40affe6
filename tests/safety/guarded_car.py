"""A car for the safety-process tests, run as its own process: ``python guarded_car.py ENDPOINT SCENARIO``.

It drives a PCA9685 register model that the test process serves (``I2CSimulator.serve``), steering on channel 1
and throttle on channel 0, at throttle 0.5 (pulse 435) and angle 0.5 (pulse 332), with the stopped pulse 370 and
the steering centre 375 as safe states. It prints ``driving`` once its commands are on the chip, then, after
half a second, ``hang`` just before the scenario's fault begins:

* ``drive``: no fault (the test kills the process);
* ``regex``: the pilot (``executor=True, timeout=0.2``, as the docs recommend for anything that can block)
  runs a catastrophic regular expression, C code that holds the GIL for many seconds;
* ``threads``: 32 CPU-bound Python threads start, and the pilot (in the executor) spins in Python for 30 s.
"""

from __future__ import annotations

import asyncio
import re
import sys
import threading
import time

from asyncdonkey import Vehicle
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.testing.i2c_models import RemoteI2CSimulator


def say(word: str) -> None:
    sys.stdout.write(word + "\n")
    sys.stdout.flush()


def spin(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


class Pilot:
    """Drives at (0.5, 0.5) until the fault is due, then runs the scenario's fault inside ``run()``."""

    def __init__(self, scenario: str) -> None:
        self.scenario = scenario
        self.fault_at: float | None = None
        self.hung = False

    def run(self) -> tuple[float, float]:
        if not self.hung and self.fault_at is not None and time.monotonic() >= self.fault_at:
            self.hung = True
            say("hang")
            if self.scenario == "threads":
                for _ in range(32):
                    threading.Thread(target=spin, args=(30.0,), daemon=True).start()
        if self.hung:  # every call from now on hangs (a timed-out call is retried on the next tick)
            if self.scenario == "regex":
                re.match(r"(a+)+$", "a" * 28 + "!")  # about 2**28 steps, all in C with the GIL held
            else:
                spin(30.0)
        return 0.5, 0.5


class Announce:
    """Says ``driving`` once, on the first tick after the ESC is armed, and schedules the fault."""

    def __init__(self, throttle: PWMThrottle, pilot: Pilot) -> None:
        self.throttle, self.pilot, self.said = throttle, pilot, False

    def run(self) -> None:
        if not self.said and self.throttle.written_pulse == 435:
            self.said = True
            say("driving")
            if self.pilot.scenario != "drive":
                self.pilot.fault_at = time.monotonic() + 0.5


async def main(endpoint: str, scenario: str) -> None:
    buses = RemoteI2CSimulator(endpoint).registry()
    steering = PWMSteering("PCA9685.1:40.1", buses=buses)
    throttle = PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0.0)
    pilot = Pilot(scenario)
    v = Vehicle(safety_process=True)
    v.add(pilot, outputs=["angle", "throttle"], executor=True, timeout=0.2, on_error="continue")
    v.add(steering, inputs=["angle"], name="steering")
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    v.add(Announce(throttle, pilot))
    await v.run(20, duration=120)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2]))
