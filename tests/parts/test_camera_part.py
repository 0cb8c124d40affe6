"""CvCamera and ImageFolderCamera as drive-loop parts."""

import asyncio
import itertools
import time

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.parts.camera import CameraError, CvCamera, ImageFolderCamera
from asyncdonkey.testing.camera_models import frame_number, write_image_folder, write_test_video


@pytest.fixture
def video(tmp_path):
    return str(write_test_video(tmp_path / "cam.avi", 200, fps=100))


class Sink:
    """Records what each tick received on ``cam/image_array``."""

    def __init__(self):
        self.frames = []

    def run(self, image):
        self.frames.append(image)


def test_constructor_waits_for_the_first_frame(video):
    cam = CvCamera(iCam=video)
    frame = cam.run_threaded()  # no thread started, no tick run: the warm-up already happened
    assert isinstance(frame, np.ndarray) and frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    assert frame_number(frame) == 0
    assert cam.outputs == ["cam/image_array"]
    cam.shutdown()


def test_missing_device_and_file_give_clear_errors(tmp_path):
    with pytest.raises(CameraError, match=r"camera 97 \(/dev/video97\)"):
        CvCamera(iCam=97)
    with pytest.raises(CameraError, match=r"missing\.avi"):
        CvCamera(iCam=str(tmp_path / "missing.avi"))
    with pytest.raises(ValueError, match="IMAGE_DEPTH"):
        CvCamera(image_d=1, iCam=str(tmp_path / "missing.avi"))


@pytest.mark.realtime
@pytest.mark.asyncio
@pytest.mark.parametrize("threaded", [False, True])
async def test_vehicle_on_the_real_loop_never_sees_none_and_frames_move_on(video, threaded):
    cam = CvCamera(iCam=video, loop=True, timestamp=True)
    sink = Sink()
    stamps = []
    v = Vehicle()
    v.add(cam, outputs=cam.outputs, threaded=threaded)
    v.add(sink, inputs=["cam/image_array"])
    v.add(lambda_part(stamps.append), inputs=["cam/timestamp"])
    report = await v.run(rate_hz=20, max_loop_count=12)
    assert report.loops == 12
    assert all(isinstance(f, np.ndarray) and f.shape == (120, 160, 3) for f in sink.frames)
    numbers = [frame_number(f) for f in sink.frames]
    assert numbers[-1] > numbers[0]  # at 100 fps against 20 Hz ticks the frames move on
    assert all(b >= a for a, b in itertools.pairwise(stamps))
    assert not cam.reader.running  # shutdown stopped the reader


def lambda_part(fn):
    class P:
        def run(self, x):
            fn(x)

    return P()


@pytest.mark.realtime
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_on_the_virtual_clock_frames_are_stamped_with_virtual_time(video):
    cam = CvCamera(iCam=video, loop=True)
    loop = asyncio.get_running_loop()
    v = Vehicle()
    v.add(cam, outputs=cam.outputs)
    v.add(RealWork(0.05), executor=True)  # real time passes (virtual time does not) so the reader grabs
    await v.run(rate_hz=20, max_loop_count=3)
    assert cam.frames > 2
    # Every frame grabbed after the first tick carries a time from the loop's clock (virtual, starting at 0).
    assert 0.0 <= cam.sample.timestamp <= loop.time()


class RealWork:
    def __init__(self, seconds):
        self.seconds = seconds

    def run(self):
        time.sleep(self.seconds)


@pytest.mark.realtime
def test_non_looping_file_ends_once_and_keeps_serving_the_last_frame(tmp_path):
    path = write_test_video(tmp_path / "short.avi", 4, fps=400)
    ended = []
    cam = CvCamera(iCam=str(path), loop=False, on_end=lambda: ended.append(True))
    cam.run()
    for _ in range(200):
        if cam.ended:
            break
        time.sleep(0.005)
    assert ended == [True]
    assert frame_number(cam.run()) == 3
    cam.shutdown()


def test_image_folder_replays_a_tub_in_index_order_and_loops(tmp_path):
    images = tmp_path / "tub" / "images"
    write_image_folder(images, 12)  # 0_..., 1_..., 10_..., 11_...: name order would put 10 before 2
    cam = ImageFolderCamera(images, loop=True)
    numbers = [frame_number(cam.run()) for _ in range(15)]
    assert numbers == [*list(range(12)), 0, 1, 2]
    assert cam.last_path.endswith("2_cam_image_array_.jpg")
    frame = cam.run()
    assert frame.shape == (120, 160, 3) and frame.dtype == np.uint8
    cam.shutdown()


def test_image_folder_glob_and_end(tmp_path):
    write_image_folder(tmp_path, 5)
    write_image_folder(tmp_path, 2, name="{index}_other_.jpg")
    ended = []
    cam = ImageFolderCamera(
        str(tmp_path / "*_cam_image_array_.jpg"), 64, 48, loop=False, on_end=lambda: ended.append(1)
    )
    numbers = [frame_number(cam.run()) for _ in range(7)]
    assert numbers == [0, 1, 2, 3, 4, 4, 4]
    assert cam.ended and ended == [1]
    assert cam.run().shape == (48, 64, 3)
    cam.shutdown()


def test_image_folder_rgb(tmp_path):
    write_image_folder(tmp_path, 1, color=(0, 0, 255))
    cam = ImageFolderCamera(tmp_path)
    lower = cam.run()[70:].reshape(-1, 3).astype(int).mean(axis=0)
    assert lower[0] > 230 and lower[1] < 25 and lower[2] < 25
    cam.shutdown()


def test_image_folder_errors_name_the_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"empty.*no image files"):
        ImageFolderCamera(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match=r"matches no files"):
        ImageFolderCamera(str(tmp_path / "*.png"))
    with pytest.raises(FileNotFoundError, match=r"neither a folder nor a glob"):
        ImageFolderCamera(tmp_path / "nowhere")
