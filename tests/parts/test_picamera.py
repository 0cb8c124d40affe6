"""PiCamera (picamera2) as a drive-loop part, against the picamera2 model: ages, buffers, a stalled camera."""

import asyncio
import itertools

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.failsafe import StaleCommandStop
from asyncdonkey.parts.picamera import PiCamera, PicameraMissing
from asyncdonkey.testing.camera_models import frame_number
from asyncdonkey.testing.picamera2_model import Picamera2Model

PERIOD = 0.05  # 20 fps: the model completes a frame one period after its exposure began


@pytest.fixture
def rig():
    return Picamera2Model(fps=20)


def camera(rig, **kw):
    return PiCamera(picamera2=rig.module, sensor_clock_ns=rig.clock_ns, **kw)


class Watch:
    def __init__(self):
        self.seen = []

    def run(self, *values):
        self.seen.append(values)


class AtTick:
    """Calls ``action`` at the end of tick ``k``."""

    def __init__(self, k, action):
        self.k, self.action, self.tick = k, action, 0

    def run(self):
        if self.tick == self.k:
            self.action()
        self.tick += 1


def test_the_constructor_warms_up_and_run_never_returns_none(rig):
    cam = camera(rig)
    image = cam.run()
    assert isinstance(image, np.ndarray) and image.shape == (120, 160, 3) and image.dtype == np.uint8
    assert cam.outputs == ["cam/image_array"]
    cam.shutdown()
    assert rig.cameras_open == []


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_frame_age_counts_from_the_exposure_not_from_the_read(rig):
    cam = camera(rig, timestamp=True)
    watch = Watch()
    v = Vehicle()
    v.add(cam, outputs=cam.outputs)
    v.add(watch, inputs=["cam/image_array", "cam/timestamp", "cam/image_array@age"])
    samples = []

    class Samples:
        def run(self):
            samples.append(cam.sample)  # the poller's newest: when it was read, and the frame it holds

    v.add(Samples())
    await v.run(rate_hz=20, max_loop_count=40)
    numbers = [frame_number(image) for image, _, _ in watch.seen]
    assert all(b - a in (0, 1) for a, b in itertools.pairwise(numbers)) and numbers[-1] - numbers[0] >= 35
    # The poller stamps a sample when it read it; the frame's origin is one frame period earlier, when its
    # exposure began: the sensor timestamp, mapped to the loop's clock.
    for sample in samples[1:]:  # (the first is the warm-up frame, read in the constructor)
        assert sample.timestamp - sample.value.origin == pytest.approx(PERIOD, abs=1e-9)
    for _, _stamp, age in watch.seen[1:]:
        assert PERIOD - 1e-9 <= age <= 2 * PERIOD + 1e-9  # never the ~0 a read-time stamp would give
    tick_times = [stamp + age for _, stamp, age in watch.seen]
    assert all(b - a == pytest.approx(0.05) for a, b in itertools.pairwise(tick_times))  # age = tick - origin


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_every_request_is_released_over_a_long_drive(rig):
    cam = camera(rig, buffer_count=4)
    v = Vehicle()
    v.add(cam, outputs=cam.outputs)
    v.add(Watch(), inputs=["cam/image_array"])
    model_cam = rig.cameras_open[0]
    held = []

    class Probe:
        def run(self):
            held.append(model_cam.app_held)  # requests handed out and not yet released

    v.add(Probe())
    await v.run(rate_hz=20, max_loop_count=400)
    assert cam.frames >= 400 and rig.frames_dropped == 0
    assert max(held) == 0  # between captures the part holds no request
    assert rig.cameras_open == []  # shutdown closed the camera


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_a_camera_that_stops_delivering_ages_its_frame_and_the_failsafe_stops_the_car(rig):
    cam = camera(rig, capture_timeout_s=0.2)

    class Pilot:
        def run(self, image):
            return 0.5 if image.mean() > 0 else 0.4  # a command computed from the image

    watch = Watch()
    v = Vehicle()
    v.add(cam, outputs=["cam/image_array"])
    v.add(Pilot(), inputs=["cam/image_array"], outputs=["throttle"])
    v.add(StaleCommandStop(max_age_s=0.25), inputs=["throttle", "throttle@age"], outputs=["throttle"])
    v.add(watch, inputs=["throttle", "throttle@age"])
    v.add(AtTick(10, rig.stall))
    await v.run(rate_hz=20, max_loop_count=30)
    throttles = [t for t, _ in watch.seen]
    ages = [a for _, a in watch.seen]
    assert throttles[:11] == [0.5] * 11 and max(ages[:11]) <= 2 * PERIOD + 1e-9
    after = ages[12:]
    assert all(b == pytest.approx(a + 0.05) for a, b in itertools.pairwise(after))  # the last frame grows old
    stopped = throttles.index(0.0)
    assert ages[stopped] >= 0.25 and ages[stopped - 1] < 0.25  # the failsafe acts the tick the age crosses
    assert throttles[stopped:] == [0.0] * (30 - stopped)
    assert cam.errors > 0 and "no frame within 0.2 s" in str(cam.poller.last_error)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_built_before_the_loop_runs_the_first_frame_is_restamped_on_the_loop_clock(rig):
    cam = await asyncio.to_thread(camera, rig)  # no running loop in that thread: stamped on time.monotonic
    watch = Watch()
    v = Vehicle()
    v.add(cam, outputs=cam.outputs)
    v.add(watch, inputs=["cam/image_array@age"])
    await v.run(rate_hz=20, max_loop_count=3)
    assert all(0 <= age <= 1.0 for (age,) in watch.seen)  # not the monotonic clock's epoch, on virtual time


@pytest.mark.realtime
@pytest.mark.asyncio
async def test_on_a_real_loop_with_real_camera_timing():
    rig = Picamera2Model(fps=20, clock="real")
    cam = camera(rig)
    watch = Watch()
    v = Vehicle()
    v.add(cam, outputs=cam.outputs)
    v.add(watch, inputs=["cam/image_array", "cam/image_array@age"])
    report = await v.run(rate_hz=20, max_loop_count=12)
    assert report.loops == 12
    numbers = [frame_number(image) for image, _ in watch.seen]
    assert numbers[-1] > numbers[0]
    assert all(PERIOD - 1e-3 <= age < 1.0 for _, age in watch.seen[1:])
    assert rig.cameras_open == [] and not rig.cameras_open


def test_a_missing_picamera2_is_one_line_naming_the_apt_package(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "picamera2", None)
    with pytest.raises(PicameraMissing, match=r"sudo apt install python3-picamera2.*--system-site-packages"):
        PiCamera()


def test_depth_other_than_rgb_is_refused(rig):
    with pytest.raises(ValueError, match="IMAGE_DEPTH"):
        camera(rig, image_d=1)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_subscribers_get_each_new_frame_with_its_exposure_origin(rig):
    cam = camera(rig)
    got = []
    unsubscribe = cam.subscribe(lambda image, origin: got.append((frame_number(image), origin)))
    v = Vehicle()
    v.add(cam, outputs=cam.outputs)
    await v.run(rate_hz=20, max_loop_count=10)
    unsubscribe()
    numbers = [n for n, _ in got]
    assert len(got) >= 9 and numbers == list(range(numbers[0], numbers[0] + len(got)))  # each frame once, in order
    assert all(b - a == pytest.approx(0.05) for (_, a), (_, b) in itertools.pairwise(got))  # 20 fps exposures
    assert got[-1][1] >= cam.output_origin()  # the subscriber saw the frame the last tick got, or a newer one
