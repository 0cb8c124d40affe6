"""A car for the safety-process tests, run as its own process: ``python guarded_car.py ENDPOINT SCENARIO``.

It drives a PCA9685 register model that the test process serves (``I2CSimulator.serve``), steering on channel 1
and throttle on channel 0, at throttle 0.5 (pulse 435) and angle 0.5 (pulse 332), with the stopped pulse 370 and
the steering centre 375 as safe states. It prints ``driving`` once its commands are on the chip, then, after
half a second, ``hang`` just before the scenario's fault begins:

* ``drive``: no fault (the test kills the process, or signals it);
* ``regex``: the pilot (``executor=True, timeout=0.2``, as the docs recommend for anything that can block)
  runs a catastrophic regular expression, C code that holds the GIL for many seconds;
* ``regex-forever``: the same, holding the GIL for minutes (longer than any test waits);
* ``threads``: 32 CPU-bound Python threads start, and the pilot (in the executor) spins in Python for 30 s;
* ``steering41``: no fault, but the steering is on a second chip at 0x41 (the test makes it NACK);
* ``regex-once``: the pilot holds the GIL once for ``HANG_S`` (a regex sized by a calibration run, so the
  length does not depend on the machine's speed), then drives on; the car stops 1.5 s after the hang;
* ``on-usr1``: no fault until SIGUSR1, then the pilot holds the GIL once for ``HANG_S`` and drives on; the car
  stops 1.5 s after the hang.

The drive runs with ``Vehicle.run_with_signals`` (SIGINT, SIGTERM, SIGHUP stop it; its safety process ends it if
it cannot), and when it ends the car prints ``report <json>`` (the report's safety figures) and the formatted
report on stdout.
"""

from __future__ import annotations

import asyncio
import json
import re
import signal
import sys
import threading
import time

from asyncdonkey import Vehicle
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.testing.i2c_models import RemoteI2CSimulator

#: how long ``regex-once`` and ``on-usr1`` hold the GIL
HANG_S = 1.5


def say(word: str) -> None:
    sys.stdout.write(word + "\n")
    sys.stdout.flush()


def spin(seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pass


def hold_gil(seconds: float) -> float:
    """Run a catastrophic regex sized to hold the GIL about ``seconds`` (C code: no thread of this process runs);
    returns how long it did. The size is found from a small run, each extra ``a`` doubling the work."""
    n, took = 16, 0.0
    while took < 0.05:
        t0 = time.monotonic()
        re.match(r"(a+)+$", "a" * n + "!")
        took = time.monotonic() - t0
        n += 1
    while took * 2 <= seconds * 1.4:
        took *= 2
        n += 1
    t0 = time.monotonic()
    re.match(r"(a+)+$", "a" * (n - 1) + "!")
    return time.monotonic() - t0


class Pilot:
    """Drives at (0.5, 0.5) until the fault is due, then runs the scenario's fault inside ``run()``."""

    def __init__(self, scenario: str) -> None:
        self.scenario = scenario
        self.fault_at: float | None = None
        self.hung = False
        self.stop_at: float | None = None

    def run(self) -> tuple[float, float]:
        if not self.hung and self.fault_at is not None and time.monotonic() >= self.fault_at:
            self.hung = True
            say("hang")
            if self.scenario == "threads":
                for _ in range(32):
                    threading.Thread(target=spin, args=(30.0,), daemon=True).start()
            elif self.scenario in ("regex-once", "on-usr1"):
                took = hold_gil(HANG_S)
                say(f"held {took:.3f}")
                self.stop_at = time.monotonic() + 1.5
                return 0.5, 0.5
        if self.hung:  # every call from now on hangs (a timed-out call is retried on the next tick)
            if self.scenario == "regex":
                re.match(r"(a+)+$", "a" * 28 + "!")  # about 2**28 steps, all in C with the GIL held
            elif self.scenario == "regex-forever":
                re.match(r"(a+)+$", "a" * 36 + "!")  # 2**36 steps: hours
            elif self.scenario == "threads":
                spin(30.0)
        return 0.5, 0.5


class Announce:
    """Says ``driving`` once, on the first tick after the ESC is armed, and schedules the fault."""

    def __init__(self, throttle: PWMThrottle, pilot: Pilot, vehicle: Vehicle) -> None:
        self.throttle, self.pilot, self.vehicle, self.said = throttle, pilot, vehicle, False

    def run(self) -> None:
        if not self.said and self.throttle.written_pulse == 435:
            self.said = True
            say("driving")
            if self.pilot.scenario not in ("drive", "steering41", "on-usr1"):
                self.pilot.fault_at = time.monotonic() + 0.5
        if self.pilot.stop_at is not None and time.monotonic() >= self.pilot.stop_at:
            self.vehicle.stop("scenario over")


async def main(endpoint: str, scenario: str) -> None:
    buses = RemoteI2CSimulator(endpoint).registry()
    steering_pin = "PCA9685.1:41.1" if scenario == "steering41" else "PCA9685.1:40.1"
    steering = PWMSteering(steering_pin, buses=buses)
    throttle = PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0.0)
    pilot = Pilot(scenario)
    if scenario == "on-usr1":
        signal.signal(signal.SIGUSR1, lambda *_: setattr(pilot, "fault_at", time.monotonic()))
    v = Vehicle(safety_process=True)
    # regex-once: a timeout shorter than the window, so the tick after the hang applies the stale command before
    # the throttle's own writer wakes (the car's deadline is then recomputed from the command's age)
    timeout = 0.1 if scenario == "regex-once" else 0.2
    v.add(pilot, outputs=["angle", "throttle"], executor=True, timeout=timeout, on_error="continue")
    v.add(steering, inputs=["angle"], name="steering")
    v.add(throttle, inputs=["throttle", "throttle@age"], name="throttle")
    v.add(Announce(throttle, pilot, v))
    report = await v.run_with_signals(20, duration=120)
    figures = {
        "unsafe_ms": report.unsafe_ms,
        "safety_process": report.safety_process,
        "stop_reason": report.stop_reason,
        "watchdog_events": report.watchdog_events,
    }
    say("report " + json.dumps(figures))
    say(v.format_report(report))


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2]))
