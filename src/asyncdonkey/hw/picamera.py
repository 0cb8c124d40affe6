"""The Raspberry Pi camera through ``picamera2`` (libcamera): RGB frames stamped with the sensor's own time.

**Where picamera2 comes from.** On Raspberry Pi OS the camera stack is libcamera, and its Python bindings exist
only as the apt package ``python3-picamera2`` (which brings ``python3-libcamera``); the ``picamera2`` on PyPI is
pure Python and cannot work without those bindings. So picamera2 is not an extra of ours: it is installed with
apt, and the car's virtual environment is made with ``python3 -m venv --system-site-packages`` so it sees apt's
packages. :func:`import_picamera2` imports it and, when it cannot, raises :class:`PicameraMissing` with that
advice in one line.

**How a frame is taken** (picamera2's recommended video-rate loop): ``create_video_configuration`` with the main
stream at the output size, format ``RGB888`` and ``FrameDurationLimits`` fixing the frame rate, ``configure``,
``start``; then per frame ``capture_request(wait=timeout)``, ``request.make_array("main")`` (a copy),
``request.get_metadata()`` and, always, ``request.release()``. Buffers are few (``buffer_count``, 4 here): a
request never released keeps its buffer from the camera, and after a few of those the camera has nothing to fill
and every capture blocks. The ISP scales the sensor image to the output size, so no resize is needed unless
libcamera adjusted the size (then the frame is resized to what was asked).

**Byte order.** picamera2's format names are DRM fourccs, which name a little-endian pixel word from its most
significant byte: ``RGB888`` arrays hold **B, G, R** in memory (what OpenCV wants), ``BGR888`` arrays hold R, G, B.
The runtime's contract is Donkeycar's ``cam/image_array``: RGB, ``uint8``, ``(height, width, 3)``. The channel
reversal (and any flip) is done in the one copy made of each frame, in the capture thread.

**When a frame was taken.** Each request's metadata carries ``SensorTimestamp``: the time the first row of the
frame started its exposure, in nanoseconds of ``CLOCK_BOOTTIME`` (libcamera's control reference defines it so;
boot time is the monotonic clock plus any time suspended). The runtime clock is ``CLOCK_MONOTONIC`` on a real
loop, the loop's virtual time on a virtual one, so the timestamp is not used as is: right after the capture
the sensor clock and the runtime clock are read together, and the frame's origin is the runtime time minus the
frame's age on the sensor clock, ``now_runtime - (now_boottime - SensorTimestamp)``. This holds for any pair of
clocks, needs no assumption that boot time equals monotonic time, and makes a frame's ``@age`` the age of the
light it recorded (exposure plus readout plus ISP plus whatever waited), not the time since it was read.

A capture that gets no frame within ``timeout_s`` raises :class:`~asyncdonkey.hw.camera.CameraError` naming the
camera (counted in ``timeouts``; the part's poller logs it at most once a second). After a timeout the driver
calls ``cancel_all_and_flush()``: picamera2 keeps a timed-out capture's job queued, and that job would take the
next frame and hold its buffer for ever. The driver does not reopen a camera that stopped: a CSI camera whose
ribbon came loose does not come back without a reboot; the part's frames grow old instead, which the car's
stale-command failsafe acts on.
"""

from __future__ import annotations

import concurrent.futures
import importlib
import threading
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from .camera import DEFAULT_IMAGE_H, DEFAULT_IMAGE_W, CameraError

__all__ = [
    "APT_PACKAGE",
    "FORMATS",
    "Frame",
    "PiCameraDriver",
    "PicameraMissing",
    "boottime_ns",
    "import_picamera2",
]

#: The Debian / Raspberry Pi OS package that provides picamera2 with its libcamera bindings.
APT_PACKAGE = "python3-picamera2"

#: picamera2 formats this driver takes, and how to get R, G, B out of each one's memory order.
FORMATS: dict[str, tuple[slice, int]] = {
    "RGB888": (slice(None, None, -1), 3),  # B, G, R in memory
    "BGR888": (slice(None), 3),  # R, G, B in memory
    "XRGB8888": (slice(2, None, -1), 4),  # B, G, R, X
    "XBGR8888": (slice(0, 3), 4),  # R, G, B, X
}


class PicameraMissing(CameraError, ImportError):
    """picamera2 (with libcamera's bindings) cannot be imported; the message says how to install it, in one line."""


def import_picamera2() -> ModuleType:
    """Import ``picamera2``, or raise :class:`PicameraMissing` saying how to install it, in one line.

    Two failures are told apart: picamera2 (or libcamera's bindings) not visible from this Python (install it
    with apt, make the venv with ``--system-site-packages``), and apt's ``simplejpeg``, which picamera2 imports,
    built for the numpy 1 of Raspberry Pi OS while the venv has numpy 2 (our dependencies bring it): numpy then
    refuses the compiled module ("numpy.dtype size changed"), and a ``simplejpeg`` wheel from PyPI, built for
    numpy 2, installed into the venv fixes it.
    """
    try:
        return importlib.import_module("picamera2")
    except (ImportError, ValueError) as exc:
        if _numpy_abi_clash(exc):
            raise PicameraMissing(
                f"picamera2 cannot be imported: a compiled module it uses was built for numpy 1 ({_first_line(exc)}); "
                "install a simplejpeg built for this venv's numpy 2 with "
                "`.venv/bin/pip install --force-reinstall --no-deps simplejpeg` (see docs/raspberry-pi.md)"
            ) from None
        if not isinstance(exc, ImportError):
            raise
        missing = getattr(exc, "name", None) or "picamera2"
        raise PicameraMissing(
            f"the Raspberry Pi camera needs picamera2 ({missing} cannot be imported): install it with "
            f"`sudo apt install {APT_PACKAGE}` and make the venv with `python3 -m venv --system-site-packages` "
            f"so it sees apt's packages (see docs/raspberry-pi.md)"
        ) from None


def _numpy_abi_clash(exc: BaseException) -> bool:
    text = str(exc)
    return "numpy" in text and ("size changed" in text or "multiarray" in text or "NumPy 1.x" in text)


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def boottime_ns() -> int:
    """``CLOCK_BOOTTIME`` in nanoseconds: the clock of libcamera's ``SensorTimestamp``."""
    return time.clock_gettime_ns(time.CLOCK_BOOTTIME)


class Frame(NamedTuple):
    """One captured frame: the RGB image, its origin on the runtime clock and the raw ``SensorTimestamp``."""

    image: np.ndarray
    origin: float
    sensor_ns: int | None


class PiCameraDriver:
    """Opens a picamera2 camera at a fixed size and rate and captures RGB frames with their origins.

    Args:
        width, height: output size (Donkeycar's ``IMAGE_W``, ``IMAGE_H``).
        framerate: frames per second, fixed with ``FrameDurationLimits``.
        camera_num: which camera (picamera2's index; 0 is the only one on most Pis).
        vflip, hflip: flip the picture (a camera mounted upside down: both).
        format: the picamera2 main-stream format (``RGB888`` default; see :data:`FORMATS`).
        buffer_count: buffers libcamera allocates (each frame of the pipeline holds one).
        timeout_s: how long a capture waits for a frame (default: four frame periods, at least 0.25 s).
        picamera2: the module to use instead of importing ``picamera2`` (tests pass a model's).
        sensor_clock_ns: the clock of ``SensorTimestamp`` (default: ``CLOCK_BOOTTIME``).
        clock: the runtime clock origins are given on (seconds; default ``time.monotonic``). The part sets it
            to its loop's clock.

    The constructor opens, configures and starts the camera; :class:`~asyncdonkey.hw.camera.CameraError` names the
    camera if that fails, :class:`PicameraMissing` if picamera2 is not installed.
    """

    def __init__(
        self,
        width: int = DEFAULT_IMAGE_W,
        height: int = DEFAULT_IMAGE_H,
        *,
        framerate: float = 20.0,
        camera_num: int = 0,
        vflip: bool = False,
        hflip: bool = False,
        format: str = "RGB888",
        buffer_count: int = 4,
        timeout_s: float | None = None,
        picamera2: ModuleType | None = None,
        sensor_clock_ns: Callable[[], int] = boottime_ns,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = f"camera {camera_num} (picamera2)"
        for what, v in (("width", width), ("height", height), ("buffer_count", buffer_count)):
            if not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
                raise ValueError(f"{self.name}: {what} must be a positive int, got {v!r}")
        if not (isinstance(framerate, int | float) and 0 < framerate <= 1000):
            raise ValueError(
                f"{self.name}: framerate must be a number of frames per second in (0, 1000], got {framerate!r}"
            )
        if format not in FORMATS:
            raise ValueError(f"{self.name}: format must be one of {sorted(FORMATS)}, got {format!r}")
        self.width, self.height = width, height
        self.framerate = float(framerate)
        self.camera_num = camera_num
        self.format = format
        self.timeout_s = float(timeout_s) if timeout_s is not None else max(0.25, 4.0 / self.framerate)
        if not self.timeout_s > 0:
            raise ValueError(f"{self.name}: timeout_s must be positive, got {timeout_s!r}")
        self.sensor_clock_ns = sensor_clock_ns
        self.clock = clock
        channels, _ = FORMATS[format]
        self._index = (
            slice(None, None, -1) if vflip else slice(None),
            slice(None, None, -1) if hflip else slice(None),
            channels,
        )
        self.frames = 0  # frames captured
        self.timeouts = 0  # captures that got no frame in time
        self.last_error: str | None = None
        self._read_lock = threading.Lock()
        self._closed = False
        module = picamera2 if picamera2 is not None else import_picamera2()
        self._cam = self._open(module, buffer_count)

    def _open(self, module: ModuleType, buffer_count: int) -> Any:
        try:
            cam = module.Picamera2(self.camera_num)
        except IndexError:  # picamera2 0.3.x: global_camera_info()[camera_num] on an empty or short list
            raise CameraError(
                f"{self.name}: libcamera detects no such camera (is the ribbon cable seated the right way round, "
                f"and does `rpicam-hello --list-cameras` list it?)"
            ) from None
        except RuntimeError as exc:
            raise CameraError(f"{self.name}: picamera2 cannot open it: {exc} (is another program using it?)") from None
        try:
            model = getattr(cam, "camera_properties", {}).get("Model")
            if model:
                self.name = f"camera {self.camera_num} (picamera2, {model})"
            period_us = round(1e6 / self.framerate)
            config = cam.create_video_configuration(
                main={"size": (self.width, self.height), "format": self.format},
                buffer_count=buffer_count,
                controls={"FrameDurationLimits": (period_us, period_us)},
            )
            cam.configure(config)
            cam.start()
        except Exception as exc:
            cam.close()
            raise CameraError(
                f"{self.name}: cannot start it at {self.width}x{self.height} {self.format}: {exc}"
            ) from None
        return cam

    # ---------------------------------------------------------------------------------------- capture
    def read(self) -> Frame:
        """Capture the next frame (blocking at most ``timeout_s``): RGB image, origin, sensor timestamp.

        Raises :class:`~asyncdonkey.hw.camera.CameraError` naming the camera when no frame comes in time or the
        camera was closed.
        """
        with self._read_lock:
            cam = self._cam
            if self._closed or cam is None:
                raise CameraError(f"{self.name}: closed")
            try:
                request = cam.capture_request(wait=self.timeout_s)
            except concurrent.futures.CancelledError:
                raise CameraError(f"{self.name}: closed while waiting for a frame") from None
            except TimeoutError:
                self._timed_out(cam)
                raise CameraError(f"{self.name}: no frame within {self.timeout_s:g} s") from None
            try:
                array = request.make_array("main")
                metadata = request.get_metadata()
            finally:
                request.release()
            r0 = self.clock()
            sensor_now = self.sensor_clock_ns()
            r1 = self.clock()
        self.frames += 1
        ts = metadata.get("SensorTimestamp")
        # (without a SensorTimestamp, not a libcamera we know: the frame is at least as old as now)
        origin = r0 if ts is None else (r0 + r1) * 0.5 - (sensor_now - ts) * 1e-9
        return Frame(self._to_rgb(array), origin, ts)

    def _to_rgb(self, array: np.ndarray) -> np.ndarray:
        rgb = np.ascontiguousarray(array[self._index])
        if rgb.shape[:2] != (self.height, self.width):
            import cv2  # libcamera chose another size: give the pilot the size it was trained on

            rgb = cv2.resize(rgb, (self.width, self.height), interpolation=cv2.INTER_AREA)
        return rgb

    def _timed_out(self, cam: Any) -> None:
        self.timeouts += 1
        self.last_error = f"no frame within {self.timeout_s:g} s"
        # The timed-out job stays queued in picamera2 and would take (and keep) the next frame's buffer.
        cancel = getattr(cam, "cancel_all_and_flush", None)
        if cancel is not None:
            cancel()

    def first_frame(self, timeout_s: float) -> Frame:
        """Capture until a frame comes, for at most ``timeout_s`` (a camera starting up may take a few frames)."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return self.read()
            except CameraError:
                if self._closed or time.monotonic() >= deadline:
                    raise CameraError(f"{self.name}: no frame within {timeout_s:g} s of starting it") from None

    # ------------------------------------------------------------------------------------------ close
    def close(self) -> None:
        """Stop and close the camera. A capture still waiting is woken (picamera2's ``cancel_all_and_flush``)."""
        if self._closed:
            return
        self._closed = True
        cam = self._cam
        if cam is None:
            return
        # Let a capture in progress finish (it is at most a frame away); a stalled one is cancelled.
        got = self._read_lock.acquire(timeout=min(self.timeout_s, 2.0 / self.framerate + 0.05))
        try:
            if not got:
                cam.cancel_all_and_flush()
            cam.stop()
            cam.close()
        finally:
            self._cam = None
            if got:
                self._read_lock.release()

    @property
    def closed(self) -> bool:
        return self._closed
