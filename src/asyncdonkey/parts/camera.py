"""Camera parts with Donkeycar's output ``cam/image_array``: a live OpenCV camera and a folder replayer.

Both give RGB ``uint8`` frames of shape ``(IMAGE_H, IMAGE_W, 3)`` (120x160x3 by default) and never hand
``None`` to the parts after them.

**Warm-up.** Donkeycar cameras return ``None`` until the first frame arrives, and a pilot or a tub writer then
fails on the first ticks. :class:`CvCamera` opens the source *and waits for its first frame in the
constructor* (bounded by ``warmup_timeout_s``; a :class:`~asyncdonkey.hw.camera.CameraError` naming the device
if nothing arrives), so the warm-up is over before the vehicle's first tick and ``run()`` never waits. This
happens in ``build()``, before the event loop drives anything, which is where a blocking wait is harmless.

**Freshness.** After construction a reader thread grabs continuously and keeps only the newest frame (see
:mod:`asyncdonkey.hw.camera`). Add the camera either way:

* ``v.add(cam, outputs=["cam/image_array"])`` — ``run()`` starts the reader thread on its first call;
* ``v.add(cam, outputs=["cam/image_array"], threaded=True)`` — Donkeycar style: the vehicle runs ``update()``
  (the reader loop) in its own thread and calls ``run_threaded()`` each tick.

``shutdown()`` stops the thread and releases the device.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import glob
import logging
import os
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..clock import get_clock
from ..hw.camera import DEFAULT_IMAGE_H, DEFAULT_IMAGE_W, CameraError, CameraReader, to_rgb
from ..latest import Sample

__all__ = ["CameraError", "CvCamera", "ImageFolderCamera"]

logger = logging.getLogger(__name__)


class CvCamera:
    """An OpenCV camera (device index, device path, video file or URL) as a drive-loop part.

    Args:
        image_w, image_h: output size (Donkeycar's ``IMAGE_W``, ``IMAGE_H``; default 160x120).
        image_d: depth; only 3 (RGB) is supported, as in Donkeycar's ``CvCam``.
        iCam: the source: a device index (Donkeycar's ``CAMERA_INDEX``), a ``/dev/video*`` path, a video file
            or a stream URL.
        framerate: pacing of a file source in frames per second (``CAMERA_FRAMERATE``); ``None`` uses the
            file's own rate. A live camera paces itself.
        loop: at the end of a file, start again (True) or end (False: ``ended`` becomes true, the last frame
            keeps being served and ``on_end`` is called once, e.g. ``vehicle.stop``).
        capture_size: ask a device for this ``(width, height)`` before resizing.
        warmup_timeout_s: how long the constructor waits for the first frame.
        clock: timestamp source for frames; default: the runtime clock of the loop that first calls ``run()``
            (``time.monotonic`` before that, which is the runtime clock on real loops).
        timestamp: also output the frame's timestamp (``cam/timestamp``) after the image.
    """

    def __init__(
        self,
        image_w: int = DEFAULT_IMAGE_W,
        image_h: int = DEFAULT_IMAGE_H,
        image_d: int = 3,
        iCam: int | str = 0,
        *,
        framerate: float | None = None,
        loop: bool = True,
        on_end: Callable[[], Any] | None = None,
        capture_size: tuple[int, int] | None = None,
        warmup_timeout_s: float = 5.0,
        clock: Callable[[], float] | None = None,
        timestamp: bool = False,
    ) -> None:
        if image_d != 3:
            raise ValueError(f"CvCamera: image_d (IMAGE_DEPTH) must be 3 (RGB), got {image_d!r}")
        if not (isinstance(warmup_timeout_s, int | float) and warmup_timeout_s > 0):
            raise ValueError(f"CvCamera: warmup_timeout_s must be a positive number, got {warmup_timeout_s!r}")
        self._clock_fixed = clock is not None
        self.reader = CameraReader(
            iCam,
            image_w,
            image_h,
            fps=framerate,
            loop=loop,
            on_end=on_end,
            capture_size=capture_size,
            clock=clock or time.monotonic,
        )
        self.name = f"CvCamera({self.reader.name})"
        try:
            self._first_frame(float(warmup_timeout_s))
        except BaseException:
            self.reader.stop()
            raise
        self.outputs: list[str] = ["cam/image_array", "cam/timestamp"] if timestamp else ["cam/image_array"]
        self._timestamp = bool(timestamp)
        self._origin = self.sample.timestamp

    def _first_frame(self, timeout: float) -> None:
        """Read until the first frame (a live camera may give a few empty reads while it starts)."""
        deadline = time.monotonic() + timeout
        while not self.reader.read_one():
            if self.reader.ended or time.monotonic() >= deadline:
                self.reader.wait_first_frame(0)  # raises CameraError naming the device and why
            time.sleep(0.01)

    # ---------------------------------------------------------------------------------------- outputs
    @property
    def sample(self) -> Sample[np.ndarray]:
        """The newest frame with its timestamp and sequence number."""
        s = self.reader.sample
        assert s is not None  # the constructor read one
        return s

    @property
    def ended(self) -> bool:
        return self.reader.ended

    @property
    def frames(self) -> int:
        return self.reader.frames

    @property
    def read_failures(self) -> int:
        return self.reader.read_failures

    def _adopt_loop_clock(self) -> None:
        if self._clock_fixed:
            return
        self._clock_fixed = True
        try:
            self.reader.clock = get_clock(asyncio.get_running_loop()).now
        except RuntimeError:
            pass  # not on an event loop: keep time.monotonic

    def run(self) -> Any:
        """The newest frame (never ``None``); starts the reader thread on the first call."""
        if not self.reader.started and not self.reader.running:
            self._adopt_loop_clock()
            self.reader.start()
        return self.run_threaded()

    def run_threaded(self) -> Any:
        self._adopt_loop_clock()
        s = self.reader.latest.sample
        assert s is not None
        self._origin = s.timestamp
        return (s.value, s.timestamp) if self._timestamp else s.value

    def output_origin(self) -> float:
        """The capture time of the frame ``run()`` returned: a frame re-served on later ticks keeps its age."""
        return self._origin

    def subscribe(self, callback: Callable[[Any, float], None]) -> Callable[[], None]:
        """Push each frame as it is captured, from the reader thread (a pipelined pilot with ``trigger`` starts
        on it at once). Only for the plain image output (``timestamp=False``)."""
        return self.reader.latest.subscribe(callback)

    def update(self) -> None:
        """Donkeycar's threaded-part loop: grab until :meth:`shutdown`."""
        self.reader.run_forever()

    def shutdown(self) -> None:
        self.reader.stop()


def _natural_key(path: str) -> tuple[Any, ...]:
    """Sort ``2_cam.jpg`` before ``10_cam.jpg``: digit runs compare as numbers (a tub's index order)."""
    name = os.path.basename(path)
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)), path


class ImageFolderCamera:
    """Replays image files as a camera: a folder (e.g. a tub's ``images/``) in index order, or a glob.

    Args:
        path_or_glob: a directory (every ``.jpg``/``.jpeg``/``.png`` in it) or a glob pattern such as
            ``"data/tub_1/images/*_cam_image_array_.jpg"``.
        image_w, image_h: output size; images of another size are resized.
        loop: after the last image, start again (True) or end (False: ``ended`` becomes true, the last image
            keeps being served, ``on_end`` is called once).

    Files are ordered by their names with digit runs compared as numbers, so a tub's ``{index}_...jpg`` come
    in recording order. Each ``run()`` serves the next image. Decoding happens one image ahead on a worker
    thread, so the tick only picks up an image that is already decoded.
    """

    EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp")

    def __init__(
        self,
        path_or_glob: str | os.PathLike[str],
        image_w: int = DEFAULT_IMAGE_W,
        image_h: int = DEFAULT_IMAGE_H,
        *,
        loop: bool = True,
        on_end: Callable[[], Any] | None = None,
    ) -> None:
        where = str(path_or_glob)
        self.name = f"ImageFolderCamera({where})"
        if os.path.isdir(where):
            files = [str(p) for p in Path(where).iterdir() if p.suffix.lower() in self.EXTENSIONS]
            what = f"folder {where!r} has no image files ({', '.join(self.EXTENSIONS)})"
        elif glob.has_magic(where):
            files = [p for p in glob.glob(where) if os.path.isfile(p)]
            what = f"pattern {where!r} matches no files"
        else:
            raise FileNotFoundError(f"{self.name}: {where!r} is neither a folder nor a glob pattern")
        if not files:
            raise FileNotFoundError(f"{self.name}: {what}")
        self.paths: list[str] = sorted(files, key=_natural_key)
        self.width = image_w
        self.height = image_h
        self.loop = bool(loop)
        self.on_end = on_end
        self.ended = False
        self.index = -1  # index into paths of the image last served
        self.frames = 0
        self.last_path: str | None = None
        self._frame: np.ndarray | None = None
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="image-folder")
        self._next: concurrent.futures.Future[np.ndarray] | None = self._pool.submit(self._load, 0)

    def _load(self, i: int) -> np.ndarray:
        path = self.paths[i]
        bgr = cv2.imread(path, cv2.IMREAD_COLOR)
        if bgr is None:
            raise CameraError(f"{self.name}: cannot decode image {path!r}")
        return to_rgb(bgr, self.width, self.height)

    def run(self) -> np.ndarray:
        """The next image (RGB); after the end of a non-looping replay, the last one."""
        if self._next is None:
            assert self._frame is not None
            return self._frame
        frame = self._next.result()
        self.index = (self.index + 1) % len(self.paths)
        self.last_path = self.paths[self.index]
        self.frames += 1
        self._frame = frame
        nxt = self.index + 1
        if nxt < len(self.paths):
            self._next = self._pool.submit(self._load, nxt)
        elif self.loop:
            self._next = self._pool.submit(self._load, 0)
        else:
            self._next = None
            self.ended = True
            if self.on_end is not None:
                self.on_end()
        return frame

    run_threaded = run

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
