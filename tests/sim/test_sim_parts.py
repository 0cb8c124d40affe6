"""The simulator's drive-loop parts on the virtual clock: camera, telemetry, actuator, scripted driver."""

import asyncio
import math

import numpy as np
import pytest

from asyncdonkey import PartError, Vehicle
from asyncdonkey.clock import get_clock
from asyncdonkey.parts.sim import TELEMETRY_OUTPUTS, CarParams, ScriptedDriver, SimCar, Simulator, default_track

TRACK = default_track()


class FrameLog:
    """Records what the camera channel held each tick, and when."""

    def __init__(self, car: SimCar) -> None:
        self.car = car
        self.seqs: list[int] = []
        self.stamps: list[float] = []
        self.ticks: list[float] = []

    def run(self, image):
        assert image is not None and image.shape == (120, 160, 3)
        s = self.car.frames.sample
        self.seqs.append(s.seq)
        self.stamps.append(s.timestamp)
        self.ticks.append(get_clock().now())


def _build(car: SimCar, driver: ScriptedDriver):
    v = Vehicle()
    v.add(car.camera, outputs=["cam/image_array"])
    v.add(car.telemetry, outputs=list(TELEMETRY_OUTPUTS))
    log = FrameLog(car)
    v.add(log, inputs=["cam/image_array"])
    v.add(driver, inputs=["sim/x", "sim/y", "sim/heading"], outputs=["user/angle", "user/throttle"])
    v.add(car, inputs=["user/angle", "user/throttle"])
    return v, log


class OffTrackWatch:
    def __init__(self) -> None:
        self.off = 0
        self.worst = 0.0

    def run(self, off, cte):
        self.off += bool(off)
        self.worst = max(self.worst, abs(cte))


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_scripted_driver_drives_two_laps_through_the_vehicle():
    car = SimCar(Simulator(TRACK))
    v, log = _build(car, ScriptedDriver(TRACK, seed=1))
    watch = OffTrackWatch()
    v.add(watch, inputs=["sim/off_track", "sim/cte"])
    report = await v.run(rate_hz=20, duration=55.0)
    assert report.loops >= 1000
    assert v.mem["sim/laps"] == 2
    assert watch.off == 0 and watch.worst < 0.25
    assert car.sim.respawns == 0
    # frames come at 20 Hz on exact deadlines; each tick sees the newest, never one older than a period
    assert car.frames_dropped == 0
    assert car.frames_rendered == pytest.approx(report.loops, abs=2)
    ages = np.array(log.ticks) - np.array(log.stamps)
    assert ages.min() >= 0 and ages.max() <= 0.05 + 1e-9
    assert np.all(np.diff(log.seqs) >= 0) and log.seqs[-1] > 1000
    # the simulation kept pace with the clock
    assert car.sim.time == pytest.approx(log.ticks[-1] - log.ticks[0], abs=0.06)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_two_runs_are_identical():
    finals = []
    for _ in range(2):
        car = SimCar(Simulator(TRACK))
        v, _log = _build(car, ScriptedDriver(TRACK, seed=5))
        await v.run(rate_hz=20, max_loop_count=200)
        finals.append((car.sim.state, v.mem["cam/image_array"].tobytes()))
    assert finals[0] == finals[1]


class Constant:
    def __init__(self, angle, throttle) -> None:
        self.value = (angle, throttle)

    def run(self):
        return self.value


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_command_takes_effect_when_the_tick_gives_it():
    p = CarParams()
    car = SimCar(Simulator(TRACK, p))
    v = Vehicle()
    v.add(car.telemetry, outputs=list(TELEMETRY_OUTPUTS))
    v.add(Constant(0.0, 0.5), outputs=["angle", "throttle"])
    v.add(car, inputs=["angle", "throttle"])
    await v.run(rate_hz=20, max_loop_count=21)
    # throttle applied from the first tick; telemetry of tick 21 is 20 periods (1 s) later
    expected = 0.5 * p.max_speed * (1 - math.exp(-1.0 / p.motor_tau))
    assert v.mem["sim/speed"] == pytest.approx(expected, rel=1e-6)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
@pytest.mark.asyncdonkey_checked(False)  # SimCar's own check, as on the car (checked mode would name Constant first)
async def test_nan_steering_stops_the_car_with_a_named_error():
    car = SimCar(Simulator(TRACK))
    v = Vehicle()
    v.add(Constant(float("nan"), 0.2), outputs=["angle", "throttle"])
    v.add(car, inputs=["angle", "throttle"])
    with pytest.raises(PartError, match=r"SimCar.*'angle'.*finite"):
        await v.run(rate_hz=20, max_loop_count=5)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_camera_has_a_frame_before_the_first_publish_and_it_changes_as_the_car_moves():
    car = SimCar(Simulator(TRACK))
    first = car.camera.run()  # no task running yet: rendered on the spot
    assert first.shape == (120, 160, 3)
    task = asyncio.ensure_future(car.update())
    car.run(0.0, 0.6)
    await get_clock().sleep(2.0)
    later = car.camera.run()
    assert car.camera.age() <= 0.05 + 1e-9
    assert not np.array_equal(first, later)
    car.shutdown()
    await task
