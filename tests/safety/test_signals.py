"""SIGINT and SIGTERM through ``asyncdonkey run``: every drive ends within a bounded time, hung parts included.

Each test runs a real car process (uvloop, real time) whose throttle drives a PCA9685 register model; a
monitor thread in the car prints every change of the throttle pulse, so the test sees what the chip did.
"""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.realtime]

CAR = textwrap.dedent(
    '''
    import asyncio, time
    from asyncdonkey import Vehicle
    from asyncdonkey.parts.actuators import PWMThrottle
    from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

    class Const:
        def run(self):
            return 0.5 + 0.0

    class AsyncHang:
        def __init__(self):
            self.n = 0
        async def run(self):
            self.n += 1
            if self.n == 10:
                print("HANG", time.monotonic(), flush=True)
                await asyncio.Event().wait()

    class SyncHang:
        def __init__(self):
            self.n = 0
        def run(self):
            self.n += 1
            if self.n == 10:
                print("HANG", time.monotonic(), flush=True)
                time.sleep(60)

    class StuckShutdown:
        def run(self):
            return None
        def shutdown(self):
            time.sleep(30)

    class PrintingPCA9685(PCA9685Model):
        """Prints each change of the throttle channel as the transfer that made it ends (any thread)."""

        def __init__(self):
            self.last = None
            super().__init__()

        def end(self):
            super().end()
            p = self.pulse(0)
            if p != self.last:
                self.last = p
                print("PULSE", time.monotonic(), p, flush=True)

    def build(args):
        sim = I2CSimulator()
        sim.attach(PrintingPCA9685(), address=0x40, bus=1)
        buses = sim.registry(retry_delay_s=0)
        v = Vehicle()
        v.add(Const(), outputs=["throttle"])
        v.add(PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0), inputs=["throttle", "throttle@age"], name="throttle")
        kind = args[0]
        if kind == "async":
            v.add(AsyncHang(), name="Pilot")
        elif kind == "sync":
            v.add(SyncHang(), name="Pilot")
        elif kind == "stuck-shutdown":
            v.add(StuckShutdown(), shutdown_timeout=0.3, name="Camera")
        return v
    '''
)


class Car:
    def __init__(self, tmp_path: Path, kind: str, *extra: str) -> None:
        car = tmp_path / "car.py"
        car.write_text(CAR)
        cmd = [sys.executable, "-m", "asyncdonkey.commands", "run", str(car), *extra, "--", kind]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []

    def wait_for(self, prefix: str, timeout: float = 10.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                break
            self.lines.append(line)
            if line.startswith(prefix):
                return line
        raise AssertionError(f"no {prefix!r} line; got {self.lines}")

    def finish(self, timeout: float) -> tuple[int, float, str]:
        """(exit status, seconds it took to exit, stderr)."""
        started = time.monotonic()
        out, err = self.proc.communicate(timeout=timeout)
        took = time.monotonic() - started
        self.lines += out.splitlines(keepends=True)
        return self.proc.returncode, took, err

    def pulses(self) -> list[tuple[float, int]]:
        return [(float(w[1]), int(w[2])) for w in (ln.split() for ln in self.lines) if w and w[0] == "PULSE"]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


@pytest.fixture
def car(tmp_path):
    made: list[Car] = []

    def make(kind: str, *extra: str) -> Car:
        c = Car(tmp_path, kind, *extra)
        made.append(c)
        return c

    yield make
    for c in made:
        c.kill()


@pytest.mark.subprocess
def test_sigint_ends_a_drive_whose_async_part_never_returns(car):
    c = car("async")
    hang_at = float(c.wait_for("HANG").split()[1])
    time.sleep(0.4)
    c.proc.send_signal(signal.SIGINT)
    status, took, err = c.finish(timeout=10)
    assert status == 0, err
    assert took < 1.0 + 2.5  # the stop grace (1 s) plus a bounded shutdown
    assert "did not return within 1.0 s of the stop request" in err
    assert "stopped by: SIGINT" in err
    # the watchdog had already stopped the car a window after the part hung
    pulses = c.pulses()
    stop = next(t for t, p in pulses if p == 370 and t > hang_at)
    # the window (0.25 s), plus room for a loaded 2-core machine: the car's watchdog thread has to be scheduled and
    # its write reach the chip model's process (the same room as test_safety_process's kill -9 and hang bounds)
    assert stop - hang_at <= 0.25 + 0.5
    assert pulses[-1][1] == 370


@pytest.mark.subprocess
def test_sigint_interrupts_a_sync_part_that_holds_the_loop(car):
    c = car("sync")
    hang_at = float(c.wait_for("HANG").split()[1])
    time.sleep(0.4)
    c.proc.send_signal(signal.SIGINT)
    status, took, err = c.finish(timeout=10)
    assert status == 0, err
    assert took < 1.0 + 2.5
    assert "part 'Pilot' interrupted: it held the loop thread" in err
    assert "stopped by: SIGINT" in err
    pulses = c.pulses()
    assert next(t for t, p in pulses if p == 370 and t > hang_at) - hang_at <= 0.25 + 0.5  # as above


@pytest.mark.subprocess
def test_a_second_sigint_exits_at_once_with_status_130_and_the_throttle_stopped(car):
    c = car("sync")
    c.wait_for("HANG")
    c.proc.send_signal(signal.SIGINT)
    time.sleep(0.1)
    c.proc.send_signal(signal.SIGINT)
    status, took, err = c.finish(timeout=10)
    assert status == 130, err
    assert took < 1.0
    assert "exiting with status 130: second SIGINT" in err
    assert c.pulses()[-1][1] == 370


@pytest.mark.subprocess
def test_sigterm_stops_like_sigint(car):
    c = car("async")
    c.wait_for("HANG")
    c.proc.send_signal(signal.SIGTERM)
    status, took, err = c.finish(timeout=10)
    assert status == 0, err
    assert took < 1.0 + 2.5
    assert "stopped by: SIGTERM" in err


@pytest.mark.subprocess
def test_a_hung_shutdown_does_not_keep_the_process_alive(car):
    c = car("stuck-shutdown", "--max-loops", "5")
    status, took, err = c.finish(timeout=20)
    assert status == 1, err
    assert took < 5.0  # not the 30 s the shutdown hangs
    assert "shutdown() did not finish within 0.3 s; abandoned" in err
    assert "shutdown of 'Camera' did not finish in time" in err


def test_signal_handlers_are_restored_after_the_drive():
    from asyncdonkey import Vehicle

    before = signal.getsignal(signal.SIGINT)
    v = Vehicle()
    v.add(type("P", (), {"run": lambda self: None})())
    v.start(rate_hz=100, max_loop_count=3)
    assert signal.getsignal(signal.SIGINT) is before
    assert os.getpid() > 0
