"""CameraReader through OpenCV's real capture path, on synthetic MJPG files."""

import itertools
import threading
import time

import numpy as np
import pytest

from asyncdonkey.hw.camera import CameraError, CameraReader, to_rgb
from asyncdonkey.testing.camera_models import frame_number, make_frame_bgr, write_test_video

from ..waiting import wait_until


@pytest.fixture
def video(tmp_path):
    return str(write_test_video(tmp_path / "numbers.avi", 100, fps=100))


def test_frames_come_in_order_rgb_resized_with_increasing_stamps(video):
    ticks = iter(range(1000))
    r = CameraReader(video, clock=lambda: float(next(ticks)))
    seen = []
    for _ in range(10):
        assert r.read_one()
        s = r.sample
        seen.append((frame_number(s.value), s.seq, s.timestamp))
    assert [n for n, _, _ in seen] == list(range(10))
    assert [q for _, q, _ in seen] == list(range(1, 11))
    assert [t for _, _, t in seen] == [float(i) for i in range(10)]
    assert r.sample.value.shape == (120, 160, 3)
    assert r.sample.value.dtype == np.uint8
    r.stop()


def test_resize_to_the_configured_size(video):
    r = CameraReader(video, width=64, height=48)
    r.read_one()
    assert r.sample.value.shape == (48, 64, 3)
    assert frame_number(r.sample.value) == 0
    r.stop()


def test_bgr_red_comes_out_red_in_rgb(tmp_path):
    path = write_test_video(tmp_path / "red.avi", 3, color=(0, 0, 255))  # pure red in OpenCV's BGR
    r = CameraReader(str(path))
    r.read_one()
    lower = r.sample.value[70:, :].reshape(-1, 3).astype(int).mean(axis=0)
    assert lower[0] > 230 and lower[1] < 25 and lower[2] < 25
    r.stop()


def test_to_rgb_swaps_channels_exactly():
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 0] = 10
    bgr[..., 2] = 200
    rgb = to_rgb(bgr, 4, 4)
    assert rgb[0, 0].tolist() == [200, 0, 10]


@pytest.mark.realtime
def test_slow_consumer_gets_the_newest_frame_not_a_buffered_one(video):
    r = CameraReader(video, loop=True)  # paced at the file's 100 fps
    r.start()
    r.wait_first_frame(2.0)
    got = []
    for _ in range(3):
        time.sleep(0.25)  # a consumer 25x slower than the camera
        s = r.sample
        got.append((s.seq, frame_number(s.value), r.frames))
    r.stop()
    for (seq, number, produced_after), nxt in itertools.pairwise(got):
        # the frame served is the one the thread grabbed last, whatever was produced in between
        assert number == (seq - 1) % 100
        assert produced_after - seq <= 2
        assert nxt[0] - seq >= 5  # many frames were skipped, none queued up for us
    assert r.running is False


@pytest.mark.realtime
def test_file_end_calls_on_end_once_and_keeps_the_last_frame(tmp_path):
    path = write_test_video(tmp_path / "short.avi", 5, fps=200)
    ended = threading.Event()
    calls = []
    r = CameraReader(str(path), loop=False, on_end=lambda: (calls.append(1), ended.set()))
    r.start()
    assert ended.wait(2.0)
    time.sleep(0.05)
    assert r.ended and calls == [1]
    assert r.frames == 5
    assert frame_number(r.sample.value) == 4
    r.stop()


def test_file_loop_wraps_around(tmp_path):
    path = write_test_video(tmp_path / "loop.avi", 4)
    r = CameraReader(str(path), loop=True)
    numbers = []
    for _ in range(10):
        assert r.read_one()
        numbers.append(frame_number(r.sample.value))
    assert numbers == [0, 1, 2, 3, 0, 1, 2, 3, 0, 1]
    assert r.loops == 2
    r.stop()


def test_missing_file_names_it(tmp_path):
    with pytest.raises(CameraError, match=r"nope\.avi.*no such file"):
        CameraReader(str(tmp_path / "nope.avi"))


def test_unopenable_file_names_it(tmp_path):
    bad = tmp_path / "garbage.avi"
    bad.write_bytes(b"not a video at all" * 10)
    with pytest.raises(CameraError, match=r"garbage\.avi.*could not open"):
        CameraReader(str(bad))


def test_missing_device_index_names_the_device():
    with pytest.raises(CameraError, match=r"camera 97 \(/dev/video97\)"):
        CameraReader(97)


def test_wait_first_frame_times_out_naming_the_source(tmp_path):
    path = write_test_video(tmp_path / "empty_start.avi", 2)
    r = CameraReader(str(path))
    with pytest.raises(CameraError, match=r"empty_start\.avi.*no frame within 0\.05 s"):
        r.wait_first_frame(0.05)  # never started: nothing read
    r.stop()


def test_make_frame_numbers_survive_jpeg_and_downscale():
    for n in (0, 1, 513, 1023):
        rgb = to_rgb(make_frame_bgr(n), 160, 120)
        assert frame_number(rgb) == n


@pytest.mark.realtime
def test_read_failures_are_counted_and_a_live_source_is_reopened(tmp_path):
    import cv2

    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f_{i:03d}.jpg"), make_frame_bgr(i))
    # An OpenCV image sequence reads like a live source: after the last image every read fails.
    r = CameraReader(str(tmp_path / "f_%03d.jpg"), reopen_after=3)
    r.start()
    # wait for the frames after the second reopen too: on a loaded machine the test can see the reopen before
    # the reader thread has read the sequence again
    wait_until(lambda: r.reopens >= 2 and r.frames >= 9, 3.0, lambda: f"2 reopens, 9 frames ({r.reopens}, {r.frames})")
    r.stop()
    assert r.reopens >= 2
    assert r.read_failures >= 6
    assert r.frames >= 9  # each reopen starts the sequence again
    assert r.last_error == "read returned no frame"
