"""The safety process: a second path to the actuators that nothing in the car's process can block.

Every test drives a PCA9685 register model served by this test process (``I2CSimulator.serve``) and reads the
chip's outputs directly. The car-process tests run the car as a process of its own (``guarded_car.py``), so it
can be killed with SIGKILL or frozen by C code that holds its GIL while this process watches the chip.

Bounds are what a loaded 2-core machine guarantees: the guard wakes at the deadline itself and writes within a
few milliseconds on a quiet machine; the tests allow hundreds.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from asyncdonkey import Vehicle
from asyncdonkey.hw.pca9685 import open_pwm_channel
from asyncdonkey.safety import GuardedOutput, SafetyProcess
from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

from ..waiting import time_when

pytestmark = [pytest.mark.realtime, pytest.mark.subprocess]

CAR = Path(__file__).with_name("guarded_car.py")
THROTTLE, STEERING = 0, 1
STOPPED, CENTRE = 370, 375
DRIVING = 435


@pytest.fixture
def served() -> Iterator[tuple[I2CSimulator, PCA9685Model]]:
    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    sim.serve()
    yield sim, pca
    sim.close()


# ------------------------------------------------------------------------------- the car as a process


class CarProcess:
    def __init__(self, endpoint: str, scenario: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(CAR), endpoint, scenario],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.stamps: dict[str, float] = {}

    def expect(self, word: str, timeout: float = 30.0) -> float:
        """Wait for the car to print ``word``; the time this process read it."""
        import select

        assert self.proc.stdout is not None
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            ready, _, _ = select.select([self.proc.stdout], [], [], 0.05)
            if ready:
                line = self.proc.stdout.readline()
                if not line:
                    break
                if line.strip() == word:
                    self.stamps[word] = time.monotonic()
                    return self.stamps[word]
        self.proc.kill()
        _, err = self.proc.communicate(timeout=10)
        raise AssertionError(f"the car never said {word!r}; its stderr:\n{err[-3000:]}")

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate(timeout=10)


def guard_pids_of(car_pid: int) -> list[int]:
    """The car's safety process(es), found through /proc (children of the car)."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == car_pid:
                found.append(int(entry))
    return found


def test_kill_9_of_the_car_leaves_the_chip_in_its_safe_state(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    sim, pca = served
    car = CarProcess(sim.endpoint or "", "drive")
    try:
        car.expect("driving")
        assert pca.pulse(THROTTLE) == DRIVING
        assert pca.pulse(STEERING) != CENTRE
        guards = guard_pids_of(car.proc.pid)
        assert guards, "the car started no safety process"
        killed = time.monotonic()
        os.kill(car.proc.pid, signal.SIGKILL)
        stopped = time_when(
            lambda: pca.pulse(THROTTLE) == STOPPED and pca.pulse(STEERING) == CENTRE,
            5.0,
            lambda: f"the safe pulses after kill -9 (still {pca.pulse(THROTTLE)}/{pca.pulse(STEERING)})",
        )
        assert stopped - killed < 1.0
        # the guard ends once the outputs are safe: it outlives the car only to stop it
        time_when(lambda: not any(Path(f"/proc/{p}").exists() for p in guards), 10.0, "the guards to end", 0.05)
    finally:
        car.kill()


def stopped_within_the_window_of_the_hang(car: CarProcess, pca: PCA9685Model) -> None:
    """The car drives, its scenario's fault begins, and the throttle shows the stopped pulse within the failsafe
    window (its last command came before the hang) plus what a loaded machine adds."""
    car.expect("driving")
    hang = car.expect("hang")
    stopped = time_when(
        lambda: pca.pulse(THROTTLE) == STOPPED,
        5.0,
        lambda: f"the throttle stopped in the hang (still {pca.pulse(THROTTLE)})",
    )
    assert stopped - hang < 0.25 + 0.5


def test_c_code_holding_the_gil_cannot_keep_the_car_driving(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    """A catastrophic regex in an ``executor=True, timeout=0.2`` pilot freezes every thread of the car for
    about ten seconds (the in-process watchdog, the timeout and signal handlers with it). The throttle's last
    command was fresh at most a tick before the hang; its deadline is 0.25 s later."""
    sim, pca = served
    car = CarProcess(sim.endpoint or "", "regex")
    try:
        stopped_within_the_window_of_the_hang(car, pca)
        assert car.proc.poll() is None  # the car is still frozen: the safety process did it
        # and it holds: nothing from the frozen car undoes it
        time.sleep(0.3)
        assert pca.pulse(THROTTLE) == STOPPED
    finally:
        car.kill()


def test_busy_threads_cannot_starve_the_car_into_driving_on(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    """32 CPU-bound Python threads beside a pilot that spins in Python: the car's own threads wait for the GIL
    behind all of them; the safety process waits for nobody."""
    sim, pca = served
    car = CarProcess(sim.endpoint or "", "threads")
    try:
        stopped_within_the_window_of_the_hang(car, pca)
    finally:
        car.kill()


# ----------------------------------------------------------------------------- the guard on its own


def start_guard(
    sim: I2CSimulator, heartbeat_timeout_s: float = 10.0, with_steering: bool = False
) -> tuple[SafetyProcess, list]:
    buses = sim.registry()
    channels = [open_pwm_channel("PCA9685.1:40.0", buses=buses)]
    outputs = [GuardedOutput("throttle", channels[0].safety_route(STOPPED) or {}, None)]
    if with_steering:
        channels.append(open_pwm_channel("PCA9685.1:40.1", buses=buses))
        outputs.append(GuardedOutput("steering", channels[1].safety_route(CENTRE) or {}, None))
    guard = SafetyProcess(outputs, heartbeat_timeout_s)
    guard.start()
    return guard, channels


def test_a_nacked_safe_write_is_retried_until_it_lands(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    sim, pca = served
    guard, (throttle,) = start_guard(sim)
    try:
        throttle.set_pulse_sync(DRIVING)
        sim.bus(1).nack(0x40, times=30)  # 30 transactions fail; the guard's first attempts among them
        guard.deadline_setter(0)(time.monotonic())  # the command is stale now
        time_when(lambda: pca.pulse(THROTTLE) == STOPPED, 5.0)
    finally:
        summary = guard.stop()
    assert summary["events"] == 1
    assert summary["failed_attempts"] >= 10
    assert summary["acted"]["throttle"]["writes"] >= 1


def test_the_safe_state_is_held_until_a_fresh_command(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    """A driving write that lands after the guard's (a stale command the car had queued) is undone; once the
    car publishes a fresh command, its writes stand."""
    sim, pca = served
    guard, (throttle,) = start_guard(sim)
    set_deadline = guard.deadline_setter(0)
    try:
        throttle.set_pulse_sync(DRIVING)
        set_deadline(time.monotonic() + 0.05)
        time_when(lambda: pca.pulse(THROTTLE) == STOPPED, 5.0)
        throttle.set_pulse_sync(DRIVING)  # stale: no new command was published
        time_when(lambda: pca.pulse(THROTTLE) == STOPPED, 5.0)
        set_deadline(time.monotonic() + 60.0)  # a fresh command ...
        throttle.set_pulse_sync(DRIVING)  # ... and its write
        time.sleep(0.5)  # several of the guard's read-backs
        assert pca.pulse(THROTTLE) == DRIVING
    finally:
        summary = guard.stop()
    assert summary["acted"]["throttle"]["writes"] == 2
    assert pca.pulse(THROTTLE) == STOPPED  # the guard's last word at the drive's end


def test_a_stopped_heartbeat_centres_the_steering_and_a_live_one_lets_go(
    served: tuple[I2CSimulator, PCA9685Model],
) -> None:
    sim, pca = served
    guard, (throttle, steering) = start_guard(sim, heartbeat_timeout_s=0.2, with_steering=True)
    try:
        throttle.set_pulse_sync(DRIVING)
        steering.set_pulse_sync(300)
        guard.deadline_setter(0)(math.inf)  # a throttle without a failsafe window: only the heartbeat covers it
        guard.ticking()
        for _ in range(20):  # 0.2 s of ticks: nothing happens
            guard.beat(time.monotonic())
            time.sleep(0.01)
        assert pca.pulse(STEERING) == 300 and pca.pulse(THROTTLE) == DRIVING
        silent = time.monotonic()  # the loop stops ticking
        safe = time_when(lambda: pca.pulse(STEERING) == CENTRE and pca.pulse(THROTTLE) == STOPPED, 5.0)
        assert 0.2 - 0.02 < safe - silent < 0.2 + 0.5
        guard.beat(time.monotonic())  # the loop is back
        assert guard.resyncs == 1  # and learns that its outputs were written behind its back
        steering.set_pulse_sync(300)
        for _ in range(30):
            guard.beat(time.monotonic())
            time.sleep(0.01)
        assert pca.pulse(STEERING) == 300
    finally:
        guard.stop()


# --------------------------------------------------------------------------- the heartbeat, in a drive


class Watcher:
    """Records every change of a channel's pulse, from a thread of this process (the model is served here)."""

    def __init__(self, pca: PCA9685Model, channel: int) -> None:
        import threading

        self.pca, self.channel = pca, channel
        self.changes: list[tuple[float, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = None
        while not self._stop.is_set():
            p = self.pca.pulse(self.channel)
            if p != last:
                self.changes.append((time.monotonic(), p))
                last = p
            time.sleep(0.0005)

    def stop(self) -> list[tuple[float, int]]:
        self._stop.set()
        self._thread.join()
        return self.changes


class Slow:
    """A pilot whose every call takes ``seconds`` (sleeping, so the GIL is free)."""

    def __init__(self, seconds: float, at: int | None = None) -> None:
        self.seconds, self.at, self.k = seconds, at, 0
        self.blocked: tuple[float, float] | None = None

    def run(self) -> tuple[float, float]:
        self.k += 1
        if self.at is None or self.k == self.at:
            t0 = time.monotonic()
            time.sleep(self.seconds)
            self.blocked = (t0, time.monotonic())
        return 0.5, 0.5


def _guarded_drive(sim: I2CSimulator, pilot: Slow, ticks: int, **add_kw) -> tuple[object, Vehicle]:
    from asyncdonkey.loop import run_blocking
    from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle

    buses = sim.registry()
    v = Vehicle(safety_process=True)
    v.add(pilot, outputs=["angle", "throttle"], **add_kw)
    v.add(PWMSteering("PCA9685.1:40.1", buses=buses), inputs=["angle"], name="steering")
    # no failsafe window on the throttle: only the heartbeat covers it, with the shortest timeout (0.25 s)
    v.add(PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0, failsafe_age_s=None), inputs=["throttle"])
    return run_blocking(v.run(20, max_loop_count=ticks)), v


def test_a_slow_awaited_pilot_is_not_a_stopped_loop(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    """Every tick awaits a 0.4 s pilot in the executor: longer than the heartbeat timeout, but the loop is free."""
    sim, pca = served
    watcher = Watcher(pca, STEERING)
    report, _ = _guarded_drive(sim, Slow(0.4), 6, executor=True)
    changes = watcher.stop()
    assert report.safety_process is not None
    assert report.safety_process["outputs"] == ["steering", "PWMThrottle"]
    assert report.safety_process["events"] == 0
    pulses = [p for _, p in changes]
    # steering went to 332 once its first command came, and stayed there until the drive's own shutdown
    assert pulses[pulses.index(332) :] == [332, CENTRE], pulses


def test_a_sync_part_holding_the_loop_stops_the_heartbeat(served: tuple[I2CSimulator, PCA9685Model]) -> None:
    sim, pca = served
    watcher = Watcher(pca, STEERING)
    pilot = Slow(1.0, at=10)
    report, v = _guarded_drive(sim, pilot, 20)
    changes = watcher.stop()
    assert pilot.blocked is not None
    t0, t1 = pilot.blocked
    centred = [t for t, p in changes if p == CENTRE and t0 <= t <= t1]
    assert centred, changes
    assert centred[0] - t0 < 0.25 + 0.3  # the heartbeat timeout after the tick began, with room for a busy machine
    # once the loop is back, the car's own target is written again
    assert any(p == 332 and t > t1 for t, p in changes), changes
    sp = report.safety_process
    assert sp is not None and sp["events"] >= 2 and sp["resyncs"] >= 1
    assert "safety process: guarded steering, PWMThrottle; " in v.format_report(report)
