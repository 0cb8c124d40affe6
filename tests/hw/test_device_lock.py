"""One owner per device: the advisory lock per I2C bus and address (``I2CBus.claim``, ``asyncdonkey.hw.owner_lock``).

The in-process tests stand in for "another process" with a flock taken on the lock file through a descriptor of
their own (flock locks of two open files conflict even within one process). The process tests run real cars
(``asyncdonkey run lock_car.py``) on a PCA9685 register model this process serves, and read the chip directly.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from asyncdonkey.hw import owner_lock
from asyncdonkey.hw.i2c import I2CBus, I2CDeviceInUse, I2CDeviceNotFound, I2CError
from asyncdonkey.hw.mpu6050 import MPU6050
from asyncdonkey.hw.pca9685 import PCA9685, open_pwm_channel, pulse_of
from asyncdonkey.parts.actuators import PWMSteering, PWMThrottle
from asyncdonkey.testing.i2c_models import I2CSimulator, MPU6050Model, PCA9685Model

from ..waiting import wait_until

HERE = Path(__file__).resolve().parent
ASYNCDONKEY = str(Path(sys.executable).with_name("asyncdonkey"))
THROTTLE, STEERING = 0, 1


@pytest.fixture
def served() -> Iterator[tuple[I2CSimulator, PCA9685Model]]:
    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    sim.attach(MPU6050Model(), address=0x68, bus=1)
    sim.serve()
    yield sim, pca
    sim.close()


def lock_path_of(sim: I2CSimulator, address: int = 0x40) -> str:
    bus = I2CBus(1, smbus_factory=sim.smbus)  # opening a bus sends the chips nothing
    try:
        path = bus.lock_path(address)
    finally:
        bus.close()
    assert path is not None
    return path


class OtherOwner:
    """Holds the lock file as another process would, naming ``pid`` as its owner."""

    def __init__(self, path: str, pid: int, command: str = "asyncdonkey run car.py", name: bool = True) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        if name:
            os.write(self.fd, json.dumps({"pid": pid, "command": command, "started": time.time()}).encode())
        self.path = path

    def close(self) -> None:
        os.unlink(self.path)
        os.close(self.fd)


# ------------------------------------------------------------------------------------------- in one process


def test_a_chip_another_owner_holds_is_refused_naming_it_before_anything_reaches_the_chip(served) -> None:
    sim, pca = served
    first = sim.registry()
    open_pwm_channel("PCA9685.1:40.0", buses=first).set_pulse_sync(435)
    first.close_all()  # this process lets go; the "other process" below takes the chip
    path = lock_path_of(sim)
    other = OtherOwner(path, os.getppid())
    try:
        before = sim.bus(1).transactions
        with pytest.raises(I2CDeviceInUse) as caught:
            open_pwm_channel("PCA9685.1:40.1", buses=sim.registry())
        err = caught.value
        started = time.strftime("%H:%M:%S", time.localtime(err.owner.started))
        assert str(err) == (
            f"PCA9685 at 0x40 on I2C bus 1 is in use by process {os.getppid()} (asyncdonkey run car.py), "
            f"started {started}: stop that car first"
        )
        assert "\n" not in str(err)
        assert isinstance(err, I2CError) and isinstance(err, OSError) and err.errno == errno.EBUSY
        assert (err.bus, err.address, err.lock_path) == (1, 0x40, path)
        assert sim.bus(1).transactions == before  # not even the probe
        assert pca.pulse(THROTTLE) == 435 and pca.running
        assert path not in owner_lock.held()
    finally:
        other.close()


def test_an_owner_that_names_nobody_is_still_refused(served) -> None:
    sim, _ = served
    path = lock_path_of(sim)
    other = OtherOwner(path, 0, name=False)
    try:
        with pytest.raises(I2CDeviceInUse, match=r"is in use by another process \(lock file .+\): stop that car"):
            PCA9685(I2CBus(1, smbus_factory=sim.smbus), 0x40)
    finally:
        other.close()


def test_steering_and_throttle_of_one_process_share_the_chip_and_its_one_lock(served) -> None:
    sim, pca = served
    path = lock_path_of(sim)
    buses = sim.registry()
    steering = PWMSteering("PCA9685.1:40.1", buses=buses)
    throttle = PWMThrottle("PCA9685.1:40.0", buses=buses)
    assert steering._channel is not None and throttle._channel is not None
    assert steering._channel.chip is throttle._channel.chip  # one driver, one init
    other_registry = sim.registry()  # even a second registry of this process may open it
    extra = open_pwm_channel("PCA9685.1:40.2", buses=other_registry)
    assert owner_lock.held()[path] == 2  # one claim per bus
    owner = owner_lock.read_owner(path)
    assert owner is not None and owner.pid == os.getpid() and owner.device == "PCA9685 at 0x40 on I2C bus 1"
    extra.set_pulse_sync(300)
    steering._channel.set_pulse_sync(332)
    assert (pca.pulse(1), pca.pulse(2)) == (332, 300)
    other_registry.close_all()
    assert owner_lock.held()[path] == 1 and os.path.exists(path)
    buses.close_all()
    assert path not in owner_lock.held() and not os.path.exists(path)  # the last user removes the file


def test_a_driver_whose_init_fails_lets_go_of_the_chip(served) -> None:
    sim, _ = served
    path = lock_path_of(sim, 0x41)
    bus = sim.registry().get(1)
    with pytest.raises(I2CDeviceNotFound):
        PCA9685(bus, 0x41)  # nothing at 0x41
    assert path not in owner_lock.held() and not os.path.exists(path)
    bus.close()


def test_the_imu_claims_its_chip_too(served) -> None:
    sim, _ = served
    bus = sim.registry().get(1)
    MPU6050(bus, 0x68)
    path = lock_path_of(sim, 0x68)
    assert owner_lock.held()[path] == 1
    bus.close()
    assert path not in owner_lock.held()


def test_a_bus_no_other_process_can_reach_has_nothing_to_lock() -> None:
    sim = I2CSimulator()  # not served
    sim.attach(PCA9685Model(), address=0x40, bus=1)
    bus = sim.registry().get(1)
    assert bus.lock_path(0x40) is None
    held = owner_lock.held()
    PCA9685(bus, 0x40)
    assert owner_lock.held() == held
    bus.close()


def test_a_served_model_is_one_chip_for_the_server_and_its_clients_and_unrelated_models_never_meet() -> None:
    from asyncdonkey.testing.i2c_models import RemoteI2CSimulator

    a, b = I2CSimulator(), I2CSimulator()
    a.bus(1), b.bus(1)
    a.serve(), b.serve()
    try:
        here = I2CBus(1, smbus_factory=a.smbus).lock_path(0x40)
        there = I2CBus(1, smbus_factory=RemoteI2CSimulator(a.endpoint or "").smbus).lock_path(0x40)
        unrelated = I2CBus(1, smbus_factory=b.smbus).lock_path(0x40)
        assert here == there == f"{a.endpoint}.i2c-1-0x40.lock"  # beside the socket
        assert here != unrelated
        assert here != I2CBus(1, smbus_factory=a.smbus).lock_path(0x41)
    finally:
        b.close()
    Path(here).touch()  # as a killed owner leaves it
    folder = os.path.dirname(here)
    a.close()
    assert not os.path.exists(here) and not os.path.exists(folder)  # the simulator's locks go with it


def test_a_bus_another_process_opens_its_own_way_is_named_by_a_digest_of_that_way() -> None:
    sim = I2CSimulator()
    sim.bus(1)

    class Opener:
        def __init__(self, where: str) -> None:
            self.where = where

        def smbus(self, n: int):
            return sim.smbus(n)

        def cross_process_opener(self, n: int) -> dict:
            return {"opener": "somewhere:open", "args": [self.where, n]}

    one = I2CBus(1, smbus_factory=Opener("x").smbus).lock_path(0x40)
    assert one == I2CBus(1, smbus_factory=Opener("x").smbus).lock_path(0x40)
    assert one != I2CBus(1, smbus_factory=Opener("y").smbus).lock_path(0x40)
    assert os.path.dirname(one or "") == owner_lock.lock_dir()
    assert os.path.basename(one or "").startswith("asyncdonkey-i2c-1-")


def test_a_real_bus_is_named_by_its_device(monkeypatch) -> None:
    import smbus2

    class Handle:
        def close(self) -> None:
            pass

    monkeypatch.setattr(smbus2, "SMBus", lambda n: Handle())
    bus = I2CBus(1, smbus_factory=smbus2.SMBus)
    assert bus.lock_path(0x40) == os.path.join(owner_lock.lock_dir(), "asyncdonkey-i2c-1-0x40.lock")


def test_the_lock_directory_falls_back_from_run_lock_to_xdg_runtime_dir_to_temp(monkeypatch, tmp_path) -> None:
    import tempfile

    monkeypatch.setattr(owner_lock, "LOCK_DIR_CANDIDATES", (str(tmp_path / "missing"),))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert owner_lock.lock_dir() == str(tmp_path)
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert owner_lock.lock_dir() == tempfile.gettempdir()
    monkeypatch.setattr(owner_lock, "LOCK_DIR_CANDIDATES", (str(tmp_path),))
    assert owner_lock.lock_dir() == str(tmp_path)


def test_the_init_turns_off_pulses_it_finds_and_names_them(caplog) -> None:
    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    earlier = sim.registry()  # a program that has ended, as far as the chip can tell
    chip = PCA9685(earlier.get(1), 0x40)
    chip.set_pulse_sync(THROTTLE, 435)
    chip.set_pulse_sync(STEERING, 332)
    earlier.close_all()
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.hw.pca9685"):
        PCA9685(sim.registry().get(1), 0x40)
    assert [r.getMessage() for r in caplog.records] == [
        "PCA9685 at 0x40 on I2C bus 1 was already generating pulses on channel 0 (435 ticks), channel 1 "
        "(332 ticks), left by a program that has ended or one that takes no device lock (Donkeycar, donkey "
        "calibrate); the init turns them off"
    ]
    assert all(pca.pulse(ch) == 0 for ch in range(16))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.hw.pca9685"):
        PCA9685(sim.registry().get(1), 0x40)  # nothing left on: nothing to say
    assert caplog.records == []


def test_pulses_left_without_auto_increment_are_read_one_register_at_a_time(caplog) -> None:
    """Donkeycar's Adafruit driver leaves MODE1.AI off: a burst read would read one register 32 times."""
    sim = I2CSimulator()
    pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
    PCA9685(sim.registry().get(1), 0x40).set_pulse_sync(5, 400)
    pca.write_register(pca.MODE1, 0x01)  # awake, ALLCALL, no auto-increment
    with caplog.at_level(logging.WARNING, logger="asyncdonkey.hw.pca9685"):
        PCA9685(sim.registry().get(1), 0x40)
    assert "on channel 5 (400 ticks), left by" in caplog.text
    assert pca.pulse(5) == 0


@pytest.fixture(scope="module")
def served_once() -> Iterator[I2CSimulator]:
    sim = I2CSimulator()
    sim.attach(PCA9685Model(), address=0x40, bus=1)
    sim.serve()
    yield sim
    sim.close()


@given(st.lists(st.tuples(st.booleans(), st.integers(0, 3)), max_size=24))
def test_in_one_process_the_lock_is_held_exactly_while_some_bus_claims_the_chip(served_once, ops) -> None:
    """Any order of opening and closing buses that claim one chip: the lock (and its file) is held while one
    of them claims it, and the last one to close lets it go."""
    path = lock_path_of(served_once)
    buses: dict[int, I2CBus] = {}
    try:
        for opening, i in ops:
            if opening and i not in buses:
                buses[i] = I2CBus(1, smbus_factory=served_once.smbus)
                assert buses[i].claim(0x40, "PCA9685") and not buses[i].claim(0x40, "PCA9685")
            elif not opening and i in buses:
                buses.pop(i).close()
            assert owner_lock.held().get(path, 0) == len(buses)
            assert os.path.exists(path) == bool(buses)
    finally:
        for bus in buses.values():
            bus.close()
    assert path not in owner_lock.held() and not os.path.exists(path)


def test_a_closed_bus_claims_nothing(served) -> None:
    sim, _ = served
    bus = I2CBus(1, smbus_factory=sim.smbus)
    bus.close()
    with pytest.raises(I2CError, match=r"I2C bus 1: claim of 0x40 on a closed bus"):
        bus.claim(0x40)
    assert lock_path_of(sim) not in owner_lock.held()


@given(st.binary(min_size=4, max_size=4))
def test_the_driver_reads_a_channel_s_pulse_as_the_chip_generates_it(registers: bytes) -> None:
    model = PCA9685Model()
    model.registers[model.LED0 : model.LED0 + 4] = registers
    assert pulse_of(registers) == model.programmed_pulse(0)


# ------------------------------------------------------------------------------------------- across processes


class Car:
    """``asyncdonkey run lock_car.py -- ENDPOINT`` as a process of its own."""

    def __init__(self, endpoint: str) -> None:
        self.proc = subprocess.Popen(
            [ASYNCDONKEY, "run", "lock_car.py", "--duration", "60", "--", endpoint],
            cwd=HERE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def expect_driving(self, timeout: float = 30.0) -> None:
        assert self.proc.stdout is not None
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if select.select([self.proc.stdout], [], [], 0.05)[0]:
                line = self.proc.stdout.readline()
                if line.strip() == "driving":
                    return
                if not line:
                    break
        self.proc.kill()
        _, err = self.proc.communicate(timeout=10)
        raise AssertionError(f"the car never drove; its stderr:\n{err[-3000:]}")

    def stop(self) -> str:
        """SIGINT (a normal stop), then its stderr."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        _, err = self.proc.communicate(timeout=30)
        return err

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate(timeout=10)


@pytest.mark.subprocess
@pytest.mark.realtime
def test_a_second_car_on_the_chip_is_refused_and_after_kill_9_of_the_first_a_new_car_starts(served) -> None:
    sim, pca = served
    endpoint = sim.endpoint or ""
    path = lock_path_of(sim)
    first = Car(endpoint)
    cars = [first]
    try:
        first.expect_driving()
        assert (pca.pulse(THROTTLE), pca.pulse(STEERING)) == (435, 332)
        owner = owner_lock.read_owner(path)
        assert owner is not None and owner.pid == first.proc.pid
        assert owner.command == f"asyncdonkey run lock_car.py --duration 60 -- {endpoint}"
        history = {ch: list(pca.history[ch]) for ch in range(16)}
        before = sim.bus(1).transactions

        second = subprocess.run(
            [ASYNCDONKEY, "run", "lock_car.py", "--", endpoint], cwd=HERE, capture_output=True, text=True, timeout=60
        )
        assert second.returncode == 2
        lines = second.stderr.splitlines()
        assert len(lines) == 1, second.stderr
        assert lines[0].startswith("asyncdonkey run: error: lock_car.py: build() raised I2CDeviceInUse: ")
        assert (
            f"PCA9685 at 0x40 on I2C bus 1 is in use by process {first.proc.pid} (asyncdonkey run lock_car.py "
            f"--duration 60 -- {endpoint}), started "
        ) in lines[0]
        assert "stop that car first" in lines[0]
        assert sim.bus(1).transactions == before  # the second car sent the chip nothing
        assert {ch: list(pca.history[ch]) for ch in range(16)} == history
        assert (pca.pulse(THROTTLE), pca.pulse(STEERING)) == (435, 332)  # still the first car's

        os.kill(first.proc.pid, signal.SIGKILL)
        first.proc.communicate(timeout=10)
        # its safety process writes the safe pulses; the lock went with the process
        wait_until(lambda: (pca.pulse(THROTTLE), pca.pulse(STEERING)) == (370, 375), 10.0, step=0.002)
        third = Car(endpoint)
        cars.append(third)
        third.expect_driving()
        assert (pca.pulse(THROTTLE), pca.pulse(STEERING)) == (435, 332)
        owner = owner_lock.read_owner(path)
        assert owner is not None and owner.pid == third.proc.pid
        err = third.stop()
        assert third.proc.returncode == 0, err
        assert "was already generating pulses on channel 0 (370 ticks), channel 1 (375 ticks)" in err
        assert not os.path.exists(path)  # a car that ends normally removes its lock file
    finally:
        for car in cars:
            car.kill()


FORKING_OWNER = """
import os, sys, time
from asyncdonkey.hw.pca9685 import open_pwm_channel
from asyncdonkey.testing.i2c_models import RemoteI2CSimulator

open_pwm_channel("PCA9685.1:40.0", buses=RemoteI2CSimulator(sys.argv[1]).registry())
if os.fork() == 0:  # a child forked without exec, which outlives its parent
    print("child", os.getpid(), flush=True)
    time.sleep(30)
    os._exit(0)
time.sleep(30)
"""


@pytest.mark.subprocess
@pytest.mark.realtime
def test_a_forked_child_does_not_keep_the_lock_after_its_parent_is_killed(served) -> None:
    sim, _ = served
    owner = subprocess.Popen(
        [sys.executable, "-c", FORKING_OWNER, sim.endpoint or ""], stdout=subprocess.PIPE, text=True
    )
    child = 0
    try:
        assert owner.stdout is not None
        word, pid = owner.stdout.readline().split()
        assert word == "child"
        child = int(pid)
        with pytest.raises(I2CDeviceInUse, match=f"in use by process {owner.pid} "):
            open_pwm_channel("PCA9685.1:40.0", buses=sim.registry())
        os.kill(owner.pid, signal.SIGKILL)
        owner.wait(timeout=10)
        os.kill(child, 0)  # the child still runs ...
        buses = sim.registry()
        open_pwm_channel("PCA9685.1:40.0", buses=buses)  # ... and does not hold the chip
        buses.close_all()
    finally:
        if owner.poll() is None:
            owner.kill()
            owner.wait(timeout=10)
        if child:
            try:
                os.kill(child, signal.SIGKILL)
            except ProcessLookupError:
                pass
