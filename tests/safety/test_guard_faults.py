"""Faults of the safety process itself, and of a car that cannot end: each ends with the throttle stopped.

The car runs as its own process (``guarded_car.py``) on PCA9685 register models served by this test process,
which watches the chips directly. Covered: a NACKing chip beside a healthy one when the car is killed (the
throttle is not held back by the other output's retries, and the log does not claim what is not true); the
guard killed or frozen (the car notices, stops its throttle, starts a new guard, and says so in its report);
SIGINT while the guard is frozen, SIGHUP; a car whose GIL is held by C code when SIGINT comes (its guard ends
it); and the unsafe time a car reports after such a hang (the guard's figure, not the hang's length).

Bounds are what a loaded 2-core machine keeps; typical figures are in docs/safety.md.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from asyncdonkey.safety.process import MAX_RESTARTS
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

from ..waiting import time_when

pytestmark = [pytest.mark.realtime, pytest.mark.subprocess]

CAR = Path(__file__).with_name("guarded_car.py")
THROTTLE, STEERING = 0, 1
STOPPED, CENTRE, DRIVING = 370, 375, 435
WINDOW_S = 0.25  # the throttle's failsafe window, and the guard's heartbeat timeout


@pytest.fixture
def chips() -> Iterator[tuple[I2CSimulator, PCA9685Model, PCA9685Model]]:
    sim = I2CSimulator()
    pca40 = sim.attach(PCA9685Model(), address=0x40, bus=1)
    pca41 = sim.attach(PCA9685Model(), address=0x41, bus=1)
    sim.serve()
    yield sim, pca40, pca41
    sim.close()


class Lines:
    """Reads one of the car's pipes on a thread: every line with the time this process read it."""

    def __init__(self, stream) -> None:
        self.lines: list[tuple[float, str]] = []
        self._cv = threading.Condition()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            with self._cv:
                self.lines.append((time.monotonic(), line.rstrip("\n")))
                self._cv.notify_all()

    def wait(self, pred: Callable[[str], bool], timeout: float) -> tuple[float, str] | None:
        end = time.monotonic() + timeout
        with self._cv:
            while True:
                hit = next(((t, ln) for t, ln in self.lines if pred(ln)), None)
                left = end - time.monotonic()
                if hit is not None or left <= 0:
                    return hit
                self._cv.wait(left)

    def text(self) -> str:
        with self._cv:
            return "\n".join(ln for _, ln in self.lines)


class Car:
    def __init__(self, endpoint: str, scenario: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(CAR), endpoint, scenario], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        self.out = Lines(self.proc.stdout)
        self.err = Lines(self.proc.stderr)

    def expect(self, word: str, timeout: float = 30.0) -> float:
        hit = self.out.wait(lambda ln: ln == word or ln.startswith(word + " "), timeout)
        if hit is None:
            self.kill()
            raise AssertionError(f"the car never said {word!r}; stdout:\n{self.out.text()}\nstderr:\n{self.err.text()}")
        return hit[0]

    def report(self, timeout: float = 10.0) -> dict:
        hit = self.out.wait(lambda ln: ln.startswith("report "), timeout)
        assert hit is not None, f"no report; stdout:\n{self.out.text()}\nstderr:\n{self.err.text()}"
        return json.loads(hit[1][len("report ") :])

    def wait(self, timeout: float) -> int:
        return self.proc.wait(timeout)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)


@pytest.fixture
def cars() -> Iterator[Callable[[str, str], Car]]:
    made: list[Car] = []

    def make(endpoint: str, scenario: str) -> Car:
        made.append(Car(endpoint, scenario))
        return made[-1]

    yield make
    for c in made:
        c.kill()


def children_of(pid: int) -> list[int]:
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def the_guard(car: Car) -> int:
    guards = [p for p in children_of(car.proc.pid) if alive(p)]
    assert len(guards) == 1, f"expected one safety process under the car, found {guards}"
    return guards[0]


class Watcher:
    """Every change of one channel's pulse, with the time the chip took it: the register model's timeline, read
    back, so a pulse held for one tick is seen even when this process was not scheduled during it."""

    def __init__(self, pca: PCA9685Model, channel: int) -> None:
        self.pca, self.channel = pca, channel

    @property
    def changes(self) -> list[tuple[float, int]]:
        return list(self.pca.pulse_changes[self.channel])

    def first(self, pulse: int, after: float) -> float | None:
        return next((t for t, p in self.changes if p == pulse and t >= after), None)

    def stop(self) -> list[tuple[float, int]]:
        return self.changes


# --------------------------------------------------------------------------- one output NACKing


def test_kill_9_with_the_steering_chip_nacking_stops_the_throttle_at_once(chips, cars) -> None:
    """Steering on chip 0x41, which NACKs every transfer; throttle on 0x40, healthy. After kill -9 of the car,
    the guard writes the throttle first and retries the steering in turn: the throttle is not held back by the
    steering's retries, and the log names the steering as not safe until it is."""
    sim, pca40, pca41 = chips
    car = cars(sim.endpoint or "", "steering41")
    car.expect("driving")
    assert pca40.pulse(THROTTLE) == DRIVING and pca41.pulse(STEERING) == 332
    guard = the_guard(car)
    sim.bus(1).nack(0x41, times=None)
    killed = time.monotonic()
    os.kill(car.proc.pid, signal.SIGKILL)
    stopped = time_when(
        lambda: pca40.pulse(THROTTLE) == STOPPED, 5.0, lambda: f"the throttle stopped (still {pca40.pulse(THROTTLE)})"
    )
    assert stopped - killed < 1.0  # typical: under 20 ms
    not_safe = car.err.wait(lambda ln: "NOT safe" in ln, 3.0)
    assert not_safe is not None, car.err.text()
    line = not_safe[1]
    assert re.search(r"throttle \([^)]*0x40[^)]*\) in its safe state; steering \([^)]*0x41[^)]*\) NOT safe", line), line
    assert "Remote I/O error" in line and "retrying" in line, line
    assert "every output written" not in car.err.text()
    assert pca41.pulse(STEERING) == 332  # truly not safe: the chip still shows the driving angle
    # the chip answers again: the steering lands, and only now does the log say every output is safe
    sim.bus(1).clear_faults(0x41)
    time_when(lambda: pca41.pulse(STEERING) == CENTRE, 5.0)
    done = car.err.wait(lambda ln: "every output written to its safe state" in ln, 5.0)
    assert done is not None, car.err.text()
    time_when(lambda: not alive(guard), 5.0, "the guard to end", 0.02)  # and the guard ends


# ------------------------------------------------------------------ the car watches its guard


@pytest.mark.parametrize("fault", ["SIGKILL", "SIGSTOP"])
def test_a_lost_guard_is_noticed_the_throttle_stopped_and_a_new_guard_started(chips, cars, fault) -> None:
    """The guard is killed (or frozen); within about one window the car logs it, stops its throttle in-process
    and starts a new guard, which then covers a 1.5 s hang of the car's GIL as the first one would have. The
    report says the guard was lost and restarted."""
    sim, pca, _ = chips
    throttle = Watcher(pca, THROTTLE)
    car = cars(sim.endpoint or "", "on-usr1")
    car.expect("driving")
    old = the_guard(car)
    hit = time.monotonic()
    os.kill(old, getattr(signal, fault))
    lost = car.err.wait(lambda ln: f"safety process {old} " in ln and "restarting it" in ln, 3.0)
    assert lost is not None, car.err.text()
    assert ("exited" if fault == "SIGKILL" else "frozen") in lost[1], lost[1]
    time_when(lambda: throttle.first(STOPPED, hit) is not None, 2.0)
    stopped = throttle.first(STOPPED, hit)
    assert stopped is not None and stopped - hit < WINDOW_S + 0.75  # typical: 10-60 ms (kill), 260-300 (stop)
    time_when(
        lambda: [p for p in children_of(car.proc.pid) if alive(p) and p != old] != [], 3.0, "a new safety process"
    )
    assert not alive(old)
    time_when(lambda: throttle.first(DRIVING, stopped) is not None, 2.0)  # it drives on
    # the new guard does the old one's job: the car's GIL is held 1.5 s, the throttle stops within the window
    os.kill(car.proc.pid, signal.SIGUSR1)
    hang = car.expect("hang")
    stop = time_when(lambda: pca.pulse(THROTTLE) == STOPPED, 3.0)
    assert stop - hang < WINDOW_S + 1.0  # typical 0.2 s; 0.86 s seen with 7 suites running
    report = car.report(15.0)
    sp = report["safety_process"]
    # the fault is the first loss; a guard starved past its heartbeat timeout on a loaded machine is also lost
    # ("frozen", by design: starved and stopped look the same from the car) and restarted, so more may follow
    first, *more = sp["lost_why"]
    assert ("exited" if fault == "SIGKILL" else "frozen") in first, (sp, car.err.text())
    assert all(why.startswith("frozen") for why in more), (sp, car.err.text())
    assert sp["restarts"] == sp["lost"] <= MAX_RESTARTS, (sp, car.err.text())
    assert car.wait(10) == 0
    assert f"lost {sp['lost']} times" in car.out.text() and f"restarted {sp['restarts']}" in car.out.text()
    throttle.stop()


def test_sigint_while_the_guard_is_frozen_exits_promptly_with_a_report(chips, cars) -> None:
    sim, pca, _ = chips
    car = cars(sim.endpoint or "", "drive")
    car.expect("driving")
    guard = the_guard(car)
    os.kill(guard, signal.SIGSTOP)
    t0 = time.monotonic()
    car.proc.send_signal(signal.SIGINT)
    status = car.wait(10)
    took = time.monotonic() - t0
    assert status == 0, car.err.text()
    assert took < 2.5  # the stop grace is not needed here; typical 0.3-0.5 s
    assert car.report(1.0)["stop_reason"] == "SIGINT"
    assert pca.pulse(THROTTLE) == STOPPED
    assert not alive(guard)


def test_sighup_ends_the_drive_like_sigterm_with_a_report(chips, cars) -> None:
    sim, pca, _ = chips
    car = cars(sim.endpoint or "", "drive")
    car.expect("driving")
    t0 = time.monotonic()
    car.proc.send_signal(signal.SIGHUP)
    assert car.wait(10) == 0, car.err.text()
    assert time.monotonic() - t0 < 2.5
    assert car.report(1.0)["stop_reason"] == "SIGHUP"
    assert "stopped by: SIGHUP" in car.out.text()
    assert pca.pulse(THROTTLE) == STOPPED


# ------------------------------------------------------------------ a car that cannot end itself


def test_sigint_to_a_car_whose_gil_is_held_is_answered_by_its_guard(chips, cars) -> None:
    """C code holds the car's GIL for hours: no Python signal handler can run. The guard hears SIGINT through the
    wakeup pipe, waits the exit grace (2 s), writes the safe state, says why, and kills the car."""
    sim, pca, _ = chips
    car = cars(sim.endpoint or "", "regex-forever")
    car.expect("driving")
    car.expect("hang")
    time.sleep(0.3)
    t0 = time.monotonic()
    car.proc.send_signal(signal.SIGINT)
    status = car.wait(10)
    took = time.monotonic() - t0
    assert status == -signal.SIGKILL
    assert 2.0 - 0.05 < took < 2.0 + 1.5  # the exit grace, and what a loaded machine adds
    line = car.err.wait(lambda ln: "killing it (SIGKILL" in ln, 2.0)
    assert line is not None, car.err.text()
    assert "did not exit within 2.0 s of SIGINT" in line[1] and "signal handler never ran" in line[1]
    assert pca.pulse(THROTTLE) == STOPPED and pca.pulse(STEERING) == CENTRE


# ------------------------------------------------------------------------------- honest unsafe time


def test_unsafe_time_after_a_gil_hang_is_what_the_chip_held(chips, cars) -> None:
    """The car's GIL is held 1.5 s: its watchdog and its loop stand still while the guard stops the throttle
    at the deadline. The report's longest unsafe interval is the guard's (deadline to its write landing), as the
    chip showed, not the hang's length."""
    sim, pca, _ = chips
    throttle = Watcher(pca, THROTTLE)
    car = cars(sim.endpoint or "", "regex-once")
    car.expect("driving")
    hang = car.expect("hang")
    held = float(car.out.wait(lambda ln: ln.startswith("held "), 10.0)[1].split()[1])  # type: ignore[index]
    report = car.report(10.0)
    throttle.stop()
    assert held > 0.5  # the car really was frozen well past the window (about 1.5 s asked)
    stopped = throttle.first(STOPPED, hang)
    assert stopped is not None and stopped - hang < WINDOW_S + 0.5  # the guard stopped the chip
    guard = report["safety_process"]["acted"]["throttle"]
    unsafe = report["unsafe_ms"].get("throttle", {"max": 0.0})
    assert guard["writes"] >= 1
    # what the car reports is the guard's own measure (deadline to its landed write), to within a few ms
    assert unsafe["events"] == 1, unsafe  # one interval, counted once
    assert unsafe["max"] <= guard["unsafe_max_ms"] + 5.0, (unsafe, guard)
    assert unsafe["max"] < 500.0, unsafe  # not the 1.5 s hang
