"""Throttle times after faults of the safety process and of a car that cannot end (docs/safety.md figures).

Run: ``.venv/bin/python tests/safety/measure_guard_faults.py`` (about a minute; each fault 3 times). Prints ms per run:
kill -9 of the car with the steering chip NACKing (kill to throttle stopped); the guard killed or frozen (to the
throttle stopped in-process); SIGHUP and SIGINT with a frozen guard (to stopped, to exit); SIGINT while C code holds
the GIL (hang to stopped, SIGINT to exit, exit status).
"""

import os
import signal
import sys
import time

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2]))
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model
from tests.safety.test_guard_faults import STOPPED, Car, Watcher, alive, the_guard
from tests.waiting import time_when


def rig():
    sim = I2CSimulator()
    a = sim.attach(PCA9685Model(), address=0x40, bus=1)
    b = sim.attach(PCA9685Model(), address=0x41, bus=1)
    sim.serve()
    return sim, a, b


def nack():
    sim, a, _b = rig()
    car = Car(sim.endpoint, "steering41")
    car.expect("driving")
    g = the_guard(car)
    sim.bus(1).nack(0x41, times=None)
    t = time.monotonic()
    os.kill(car.proc.pid, 9)
    s = time_when(lambda: a.pulse(0) == STOPPED, 5)
    sim.bus(1).clear_faults()
    time_when(lambda: not alive(g), 5)
    car.kill()
    sim.close()
    return s - t


def lost(sig):
    sim, a, _b = rig()
    w = Watcher(a, 0)
    car = Car(sim.endpoint, "drive")
    car.expect("driving")
    g = the_guard(car)
    t = time.monotonic()
    os.kill(g, sig)
    time_when(lambda: w.first(STOPPED, t) is not None, 3)
    s = w.first(STOPPED, t)
    car.proc.send_signal(signal.SIGINT)
    car.wait(10)
    w.stop()
    sim.close()
    return s - t


def sighup():
    sim, a, _b = rig()
    car = Car(sim.endpoint, "drive")
    car.expect("driving")
    t = time.monotonic()
    car.proc.send_signal(signal.SIGHUP)
    s = time_when(lambda: a.pulse(0) == STOPPED, 5)
    car.wait(10)
    x = time.monotonic()
    sim.close()
    return s - t, x - t


def sigint_frozen():
    sim, a, _b = rig()
    car = Car(sim.endpoint, "drive")
    car.expect("driving")
    g = the_guard(car)
    os.kill(g, signal.SIGSTOP)
    t = time.monotonic()
    car.proc.send_signal(signal.SIGINT)
    s = time_when(lambda: a.pulse(0) == STOPPED, 5)
    car.wait(10)
    x = time.monotonic()
    sim.close()
    return s - t, x - t


def sigint_gil():
    sim, a, _b = rig()
    car = Car(sim.endpoint, "regex-forever")
    car.expect("driving")
    h = car.expect("hang")
    s = time_when(lambda: a.pulse(0) == STOPPED, 5)
    time.sleep(0.3)
    t = time.monotonic()
    car.proc.send_signal(signal.SIGINT)
    st = car.wait(10)
    x = time.monotonic()
    sim.close()
    return s - h, x - t, st


if __name__ == "__main__":
    N = 3
    for name, fn in [
        ("nack kill9", nack),
        ("guard SIGKILL", lambda: lost(9)),
        ("guard SIGSTOP", lambda: lost(signal.SIGSTOP)),
        ("SIGHUP (stop, exit)", sighup),
        ("SIGINT guard frozen (stop, exit)", sigint_frozen),
        ("SIGINT GIL hang (stop since hang, exit, status)", sigint_gil),
    ]:
        r = [fn() for _ in range(N)]
        print(
            name,
            [
                tuple(round(v * 1e3) if isinstance(v, float) else v for v in (x if isinstance(x, tuple) else (x,)))
                for x in r
            ],
            flush=True,
        )
