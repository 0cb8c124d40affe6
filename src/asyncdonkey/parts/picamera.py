"""The Raspberry Pi camera (picamera2, libcamera) as a drive-loop part with Donkeycar's ``cam/image_array``.

Drop-in for Donkeycar's ``PiCamera(image_w, image_h, image_d, vflip, hflip)``: RGB ``uint8`` frames of shape
``(IMAGE_H, IMAGE_W, 3)``, never ``None``. The driver (:mod:`asyncdonkey.hw.picamera`) says how frames are taken
and stamped; this part adds what the drive loop needs:

* **Warm-up in the constructor**, as :class:`~asyncdonkey.parts.camera.CvCamera`: the camera is opened, started
  and its first frame captured before the first tick (bounded by ``warmup_timeout_s``; a
  :class:`~asyncdonkey.hw.camera.CameraError` naming the camera otherwise), so ``run()`` never waits and never
  returns ``None``.
* **Capture off the loop.** ``update()`` runs a :class:`~asyncdonkey.poller.Poller` at ``framerate``: in a drive it
  captures just before the ticks (its thread, never the loop's), and picamera2 hands it the newest completed
  frame, so each tick gets the freshest frame there is without the thread waking at the camera's rate.
* **True ages.** ``output_origin()`` is the frame's exposure time mapped to the runtime clock (see the driver), so
  ``cam/image_array@age`` counts from when the light was recorded. If the camera stops delivering, the last frame
  keeps being served and its age grows; a stale-command failsafe after the pilot (``PWMThrottle``'s own, or
  :class:`~asyncdonkey.parts.failsafe.StaleCommandStop`) then stops the car. Timeouts are counted in ``errors``
  and logged at most once a second, naming the camera.

``shutdown()`` stops the poller and closes the camera.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any

import numpy as np

from ..clock import get_clock
from ..hw.camera import DEFAULT_IMAGE_H, DEFAULT_IMAGE_W, CameraError
from ..hw.picamera import Frame, PiCameraDriver, PicameraMissing, boottime_ns
from ..latest import Sample
from ..poller import Poller

__all__ = ["CameraError", "PiCamera", "PicameraMissing"]


def _runtime_clock() -> Callable[[], float]:
    """The clock of the running loop, or ``time.monotonic`` (the runtime clock of real loops) outside one."""
    try:
        return get_clock(asyncio.get_running_loop()).now
    except RuntimeError:
        return time.monotonic


class PiCamera:
    """A picamera2 camera as a part (Donkeycar's ``PiCamera`` arguments first).

    Args:
        image_w, image_h: output size (``IMAGE_W``, ``IMAGE_H``; default 160x120).
        image_d: depth; only 3 (RGB), as :class:`~asyncdonkey.parts.camera.CvCamera`.
        vflip, hflip: flip the picture (``CAMERA_VFLIP``, ``CAMERA_HFLIP``).
        framerate: frames per second (``CAMERA_FRAMERATE``); also the rate the part captures at.
        camera_num: which camera (``CAMERA_INDEX``).
        buffer_count, capture_timeout_s, format: see :class:`~asyncdonkey.hw.picamera.PiCameraDriver`.
        warmup_timeout_s: how long the constructor waits for the first frame.
        timestamp: also output the frame's origin (``cam/timestamp``, runtime clock) after the image.
        picamera2: the picamera2 module to use (default: ``import picamera2``; tests pass a model's).
        sensor_clock_ns: the clock of ``SensorTimestamp`` (default ``CLOCK_BOOTTIME``; tests pass a model's).
    """

    def __init__(
        self,
        image_w: int = DEFAULT_IMAGE_W,
        image_h: int = DEFAULT_IMAGE_H,
        image_d: int = 3,
        vflip: bool = False,
        hflip: bool = False,
        *,
        framerate: float = 20.0,
        camera_num: int = 0,
        buffer_count: int = 4,
        capture_timeout_s: float | None = None,
        format: str = "RGB888",
        warmup_timeout_s: float = 5.0,
        timestamp: bool = False,
        picamera2: ModuleType | None = None,
        sensor_clock_ns: Callable[[], int] = boottime_ns,
    ) -> None:
        if image_d != 3:
            raise ValueError(f"PiCamera: image_d (IMAGE_DEPTH) must be 3 (RGB), got {image_d!r}")
        if not (isinstance(warmup_timeout_s, int | float) and warmup_timeout_s > 0):
            raise ValueError(f"PiCamera: warmup_timeout_s must be a positive number, got {warmup_timeout_s!r}")
        self.driver = PiCameraDriver(
            image_w,
            image_h,
            framerate=framerate,
            camera_num=camera_num,
            vflip=vflip,
            hflip=hflip,
            format=format,
            buffer_count=buffer_count,
            timeout_s=capture_timeout_s,
            picamera2=picamera2,
            sensor_clock_ns=sensor_clock_ns,
            clock=_runtime_clock(),
        )
        self.name = f"PiCamera({self.driver.name})"
        self.poller: Poller[Frame] = Poller(self._read, framerate, name=self.driver.name)
        try:
            first = self.driver.first_frame(float(warmup_timeout_s))
        except BaseException:
            self.driver.close()
            raise
        self.poller.latest.publish(first, first.origin)
        self.outputs: list[str] = ["cam/image_array", "cam/timestamp"] if timestamp else ["cam/image_array"]
        self._timestamp = bool(timestamp)
        self._origin = first.origin
        self._clock_adopted = False

    # ---------------------------------------------------------------------------------------- outputs
    @property
    def sample(self) -> Sample[Frame]:
        """The newest frame (``.value``: image, origin, sensor timestamp) as the poller published it."""
        s = self.poller.latest.sample
        assert s is not None  # the constructor published the first frame
        return s

    @property
    def frames(self) -> int:
        return self.driver.frames

    @property
    def errors(self) -> int:
        """Captures that failed (no frame in time), as the poller counted them."""
        return self.poller.errors

    def run(self) -> Any:
        """The newest frame (never ``None``)."""
        if not self._clock_adopted:
            self._adopt_loop_clock()
        frame = self.poller.latest.sample[0]  # type: ignore[index]
        self._origin = frame.origin
        return (frame.image, frame.origin) if self._timestamp else frame.image

    run_threaded = run

    def output_origin(self) -> float:
        """When the frame ``run()`` returned was exposed (runtime clock): a frame re-served keeps its age."""
        return self._origin

    def subscribe(self, callback: Callable[[np.ndarray, float], None]) -> Callable[[], None]:
        """Call ``callback(image, origin)`` from the capture thread for each new frame (a pipelined pilot with
        ``trigger`` starts on it at once). Returns the unsubscriber."""

        last: list[Frame | None] = [None]

        def on_frame(frame: Frame, _read_time: float) -> None:
            if frame is not last[0]:  # (a read racing shutdown gives the newest frame back: not a new one)
                last[0] = frame
                callback(frame.image, frame.origin)

        return self.poller.latest.subscribe(on_frame)

    async def update(self) -> None:
        """Capture at ``framerate`` off the loop until shutdown."""
        self._adopt_loop_clock()
        await self.poller.update()

    def _adopt_loop_clock(self) -> None:
        """Stamp frames on the clock of the loop the part runs on, from its first tick or ``update()`` on."""
        self._clock_adopted = True
        try:
            now = get_clock(asyncio.get_running_loop()).now
        except RuntimeError:
            return  # called outside a loop: keep time.monotonic
        if self.driver.clock is not now:
            self.driver.clock = now
            self._restamp(now)

    def _restamp(self, now: Callable[[], float]) -> None:
        """The warm-up frame was stamped on another clock (built before the loop ran): map it onto this one."""
        s = self.poller.latest.sample
        if s is None or s.value.sensor_ns is None:
            return
        frame = s.value
        origin = now() - (self.driver.sensor_clock_ns() - frame.sensor_ns) * 1e-9
        self.poller.latest.publish(frame._replace(origin=origin), origin)
        self._origin = origin

    def _read(self) -> Frame:
        """The poller's read. One that starts as the part shuts down (the poller's last, racing ``shutdown()``)
        gives back the newest frame unchanged: nothing new, and no "camera closed" error to count or log."""
        try:
            return self.driver.read()
        except CameraError:
            sample = self.poller.latest.sample
            if self.driver.closed and sample is not None:
                return sample.value
            raise

    def shutdown(self) -> None:
        self.poller.shutdown()
        self.driver.close()
