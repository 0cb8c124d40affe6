"""The picamera2 driver against the picamera2 model: byte order, sizes, sensor-time origins, buffers, faults."""

import concurrent.futures
import sys
import threading
import time

import numpy as np
import pytest

from asyncdonkey.hw.camera import CameraError
from asyncdonkey.hw.picamera import APT_PACKAGE, PiCameraDriver, PicameraMissing, import_picamera2
from asyncdonkey.testing.camera_models import frame_number, make_frame_bgr
from asyncdonkey.testing.picamera2_model import Picamera2Model, Picamera2ModelHang

RED, BLUE = (255, 0, 0), (0, 0, 255)


def red_below(k, w, h):
    """A scene: the frame number on top, pure red (RGB) below."""
    return np.ascontiguousarray(make_frame_bgr(k, w, h, color=(0, 0, 255))[..., ::-1])


@pytest.fixture
def rig():
    """A picamera2 model installed as the `picamera2` module the driver imports."""
    r = Picamera2Model(fps=20, scene=red_below)
    with r.installed():
        yield r


def open_driver(rig, **kw):
    return PiCameraDriver(sensor_clock_ns=rig.clock_ns, **kw)


@pytest.mark.parametrize("fmt", ["RGB888", "BGR888", "XRGB8888", "XBGR8888"])
def test_frames_are_rgb_at_the_configured_size_whatever_the_memory_order(rig, fmt):
    cam = open_driver(rig, width=160, height=120, format=fmt)
    frame = cam.read()
    assert frame.image.shape == (120, 160, 3) and frame.image.dtype == np.uint8
    assert frame.image.flags.c_contiguous
    assert tuple(frame.image[100, 80]) == RED  # the bottom half is red in the scene
    cam.close()


def test_the_model_gives_rgb888_as_b_g_r_in_memory_like_picamera2(rig):
    """The fact the driver's conversion rests on: picamera2's RGB888 is B, G, R in memory, BGR888 is R, G, B."""
    cam = rig.module.Picamera2(0)
    for fmt, pixel in (("RGB888", BLUE), ("BGR888", RED)):
        cam.configure(cam.create_video_configuration(main={"size": (64, 48), "format": fmt}))
        cam.start()
        req = cam.capture_request(wait=1.0)
        assert tuple(req.make_array("main")[40, 30]) == pixel
        req.release()
        cam.stop()
    cam.close()


def test_flips_and_a_size_libcamera_adjusted(rig):
    cam = open_driver(rig, width=161, height=121, vflip=True, hflip=True)  # aligned down to 160x120 by picamera2
    frame = cam.read()
    assert frame.image.shape == (121, 161, 3)  # resized back to what was asked
    assert tuple(frame.image[10, 80]) == RED  # upside down: red is on top now
    cam.close()


def test_frames_come_in_order_and_the_rate_is_set_with_frame_duration_limits(rig):
    cam = open_driver(rig, framerate=25)
    frames = [cam.read() for _ in range(10)]
    numbers = [frame_number(f.image) for f in frames]
    assert numbers == list(range(numbers[0], numbers[0] + 10))
    gaps = np.diff([f.sensor_ns for f in frames])
    assert set(gaps.tolist()) == {40_000_000}  # 25 fps: 40 ms between exposures
    cam.close()


def test_the_origin_is_the_sensor_timestamp_mapped_to_the_runtime_clock(rig):
    """origin = runtime now - (sensor now - SensorTimestamp): the sensor clock's own epoch does not matter."""
    runtime = [500.0]  # a runtime clock with another epoch than the sensor's
    cam = open_driver(rig, clock=lambda: runtime[0])
    frame = cam.read()
    age_on_sensor = (rig.clock_ns() - frame.sensor_ns) * 1e-9
    assert age_on_sensor == pytest.approx(0.05)  # a frame is complete one frame period after its exposure began
    assert frame.origin == pytest.approx(500.0 - age_on_sensor, abs=1e-12)
    cam.close()


@pytest.mark.realtime
@pytest.mark.parametrize("suspended_s", [0.0, 3600.0])
def test_on_real_clocks_the_age_is_exposure_based_even_when_boottime_is_ahead_of_monotonic(suspended_s):
    """Real CLOCK_BOOTTIME, as libcamera stamps, possibly an hour ahead of CLOCK_MONOTONIC after a suspend:
    origins land on the monotonic clock, one frame period (plus what a loaded machine adds) before the read."""
    r = Picamera2Model(fps=50, clock="real", suspended_s=suspended_s)
    cam = PiCameraDriver(picamera2=r.module, framerate=50, sensor_clock_ns=r.clock_ns)
    try:
        for _ in range(5):
            frame = cam.read()
            read_at = time.monotonic()
            assert 0.02 - 1e-3 <= read_at - frame.origin < 0.02 + 1.0
    finally:
        cam.close()


def test_the_default_sensor_clock_is_boottime():
    from asyncdonkey.hw.picamera import boottime_ns

    before = time.clock_gettime_ns(time.CLOCK_BOOTTIME)
    assert before <= boottime_ns() <= time.clock_gettime_ns(time.CLOCK_BOOTTIME)
    assert PiCameraDriver.__init__.__kwdefaults__["sensor_clock_ns"] is boottime_ns


def test_a_thousand_frames_with_four_buffers_release_every_request(rig):
    cam = open_driver(rig, buffer_count=4)
    seen = [frame_number(cam.read().image) for _ in range(1000)]
    model_cam = rig.cameras_open[0]
    assert model_cam.app_held == 0 and model_cam.orphan_jobs == 0
    assert model_cam.queued + len(model_cam._ready) == 4  # every buffer is back with the camera or picamera2
    assert seen == [(seen[0] + i) % 1024 for i in range(1000)]  # no frame lost: none ever lacked a buffer
    assert rig.frames_dropped == 0
    cam.close()


def test_the_model_stalls_a_reader_that_does_not_release():
    """The model is not lenient: a reader that keeps its requests runs the pool dry as on the real camera."""
    r = Picamera2Model(fps=20)
    cam = r.module.Picamera2(0)
    cam.configure(cam.create_video_configuration(main={"size": (64, 48), "format": "RGB888"}, buffer_count=4))
    cam.start()
    kept = [cam.capture_request(wait=1.0) for _ in range(4)]
    with pytest.raises(concurrent.futures.TimeoutError):
        cam.capture_request(wait=1.0)
    with pytest.raises(Picamera2ModelHang):
        cam.capture_request()  # the real one would block for ever
    kept[0].release()
    cam.cancel_all_and_flush()  # else the timed-out captures' jobs take the freed buffer's next frame
    assert cam.capture_request(wait=1.0).frame > kept[-1].frame
    with pytest.raises(RuntimeError, match="Stream 'main' is not defined"):
        kept[0].make_array("main")  # released: its buffer is the camera's again
    cam.close()


def test_a_timed_out_capture_leaks_a_buffer_unless_flushed():
    """picamera2 keeps a timed-out capture's job; it takes the next frame and never gives it back."""
    r = Picamera2Model(fps=20)
    cam = r.module.Picamera2(0)
    cam.configure(cam.create_video_configuration(main={"size": (64, 48), "format": "RGB888"}, buffer_count=4))
    cam.start()
    r.stall()
    with pytest.raises(concurrent.futures.TimeoutError):
        cam.capture_request(wait=0.2)
    r.resume()
    cam.capture_request(wait=1.0).release()
    assert cam.app_held == 1  # the orphan job holds one buffer for good
    cam.close()


def test_a_camera_that_stops_delivering_times_out_naming_it_and_recovers_without_leaking(rig):
    cam = open_driver(rig, timeout_s=0.2)
    cam.read()
    rig.stall()
    for _ in range(10):
        with pytest.raises(CameraError, match=r"camera 0 \(picamera2, imx219\): no frame within 0.2 s"):
            cam.read()
    assert cam.timeouts == 10
    rig.resume()
    frames = [cam.read() for _ in range(20)]
    assert len({f.sensor_ns for f in frames}) == 20
    model_cam = rig.cameras_open[0]
    assert model_cam.app_held == 0 and model_cam.orphan_jobs == 0  # flushed after each timeout
    cam.close()


def test_an_unplugged_camera_gives_a_clear_error_naming_it(rig):
    rig.unplug()
    with pytest.raises(CameraError, match=r"camera 0 \(picamera2\): libcamera detects no such camera") as info:
        open_driver(rig)
    assert "rpicam-hello --list-cameras" in str(info.value)
    with pytest.raises(CameraError, match=r"camera 3 \(picamera2\): libcamera detects no such camera"):
        PiCameraDriver(picamera2=Picamera2Model(cameras=1).module, camera_num=3)


def test_a_camera_in_use_says_so(rig):
    first = open_driver(rig)
    with pytest.raises(CameraError, match=r"camera 0 \(picamera2\): picamera2 cannot open it: .*another program"):
        open_driver(rig)
    first.close()
    open_driver(rig).close()  # free again once closed


def test_missing_picamera2_gives_the_apt_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "picamera2", None)  # `import picamera2` raises ImportError
    with pytest.raises(PicameraMissing) as info:
        PiCameraDriver()
    message = str(info.value)
    assert "\n" not in message
    assert f"sudo apt install {APT_PACKAGE}" in message and "--system-site-packages" in message
    assert isinstance(info.value, ImportError) and isinstance(info.value, CameraError)


def test_missing_libcamera_bindings_name_the_module(monkeypatch):
    """picamera2 from PyPI in a venv without system site packages: it is libcamera that fails to import."""

    class Finder:
        def find_spec(self, name, path=None, target=None):
            if name == "picamera2":
                raise ModuleNotFoundError("No module named 'libcamera'", name="libcamera")
            return None

    monkeypatch.delitem(sys.modules, "picamera2", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Finder(), *sys.meta_path])
    with pytest.raises(PicameraMissing, match=r"libcamera cannot be imported"):
        import_picamera2()


@pytest.mark.realtime
@pytest.mark.parametrize(
    "error",
    [
        ValueError("numpy.dtype size changed, may indicate binary incompatibility. Expected 96 from C header, got 88"),
        ImportError("numpy.core.multiarray failed to import"),
    ],
)
def test_apt_simplejpeg_built_for_numpy_1_gets_its_own_hint(monkeypatch, error):
    """picamera2 imports apt's simplejpeg, compiled for Raspberry Pi OS's numpy 1; the venv has numpy 2."""

    class Finder:
        def find_spec(self, name, path=None, target=None):
            if name == "picamera2":
                raise error
            return None

    monkeypatch.delitem(sys.modules, "picamera2", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Finder(), *sys.meta_path])
    with pytest.raises(PicameraMissing) as info:
        import_picamera2()
    assert "pip install --force-reinstall --no-deps simplejpeg" in str(info.value) and "\n" not in str(info.value)
    assert "apt install" not in str(info.value)


@pytest.mark.realtime  # a real-clock camera model, a reader thread, and a wall-clock bound on close()
def test_close_wakes_a_capture_waiting_on_a_stalled_camera():
    r = Picamera2Model(fps=20, clock="real")
    cam = PiCameraDriver(picamera2=r.module, sensor_clock_ns=r.clock_ns, timeout_s=30.0)
    cam.read()
    r.stall()
    errors = []

    def reader():
        try:
            cam.read()
        except CameraError as exc:
            errors.append(str(exc))

    t = threading.Thread(target=reader)
    t.start()
    time.sleep(0.05)
    started = time.monotonic()
    cam.close()
    t.join(10)
    assert not t.is_alive() and time.monotonic() - started < 10  # not the 30 s timeout
    assert errors and "closed while waiting" in errors[0]
    assert r.cameras_open == []
