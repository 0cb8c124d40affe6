"""OpenCV capture that always serves the newest frame, as RGB at the configured size, stamped and numbered.

Why a reader thread: ``cv2.VideoCapture`` queues frames (V4L2 typically keeps four buffers). A drive loop that
calls ``read()`` once per tick at 20 Hz while the camera delivers 30 fps falls further and further behind and
steers on images hundreds of milliseconds old. :class:`CameraReader` grabs in its own thread as fast as the
source delivers and keeps only the newest converted frame in a :class:`~asyncdonkey.latest.Latest` cell; a
consumer never sees a frame older than the one the thread last grabbed.

The runtime's image contract is Donkeycar's: RGB, ``uint8``, shape ``(height, width, 3)`` (160x120 by
default). OpenCV decodes to BGR, so every frame is converted once, in the reader thread, off the loop.

Sources:

* **A device index** (``0`` → ``/dev/video0``) or a device path: paced by the camera itself (``read()`` blocks
  until the next frame). OpenCV's image-sequence patterns (``frame_%03d.jpg``) are read like a device.
* **A file or URL** (an ``.avi``/``.mp4``, an RTSP/HTTP stream): a file is decoded as fast as the CPU allows,
  so the reader paces it at ``fps`` (default: the file's own frame rate) to behave like a camera. At the end of
  a file the reader either starts again (``loop=True``) or ends (``ended`` becomes true, ``on_end`` is called
  once, and the last frame stays available).

Failures are named and counted: a source that cannot be opened raises :class:`CameraError` naming it; a
failed read on a live source is counted in ``read_failures`` (logged at most once a second) and after
``reopen_after`` failures in a row the capture is released and opened again.

Timestamps come from ``clock`` (seconds). The default is ``time.monotonic``, which is the runtime clock on real
event loops; a part running on the virtual clock sets ``clock`` to the loop's clock (see
:class:`asyncdonkey.parts.camera.CvCamera`).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from ..errors import AsyncdonkeyError
from ..latest import Latest, Sample
from ..ratelimit import LogThrottle

__all__ = ["DEFAULT_IMAGE_H", "DEFAULT_IMAGE_W", "CameraError", "CameraReader", "describe_source", "to_rgb"]

logger = logging.getLogger(__name__)

DEFAULT_IMAGE_W = 160
DEFAULT_IMAGE_H = 120


class CameraError(AsyncdonkeyError, RuntimeError):
    """A camera source cannot be opened or gives no frames. The message names the source."""


def describe_source(source: int | str) -> str:
    """A human name for a capture source: ``camera 0 (/dev/video0)`` or the path/URL itself."""
    if isinstance(source, int):
        return f"camera {source} (/dev/video{source})"
    return repr(str(source))


def to_rgb(frame_bgr: np.ndarray, width: int, height: int) -> np.ndarray:
    """OpenCV's BGR frame → a contiguous RGB ``uint8`` array of shape ``(height, width, 3)``.

    Resizing happens first (fewer pixels to convert when shrinking); ``INTER_AREA`` averages the source pixels,
    which is what a downscale wants (no aliasing of fine lines such as a track's edge).
    """
    if frame_bgr.ndim == 2:
        frame_bgr = cv2.cvtColor(frame_bgr, cv2.COLOR_GRAY2BGR)
    h, w = frame_bgr.shape[:2]
    if (w, h) != (width, height):
        interp = cv2.INTER_AREA if w > width or h > height else cv2.INTER_LINEAR
        frame_bgr = cv2.resize(frame_bgr, (width, height), interpolation=interp)
    return cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2RGB)


def _is_file_source(source: int | str) -> bool:
    """True for a regular file (paced and possibly looped); devices and URLs are paced by their producer."""
    return isinstance(source, str) and os.path.isfile(source)


class CameraReader:
    """Reads a ``cv2.VideoCapture`` source in a thread, keeping only the newest RGB frame.

    Args:
        source: a device index (``int``), a device path, a video file or a stream URL.
        width, height: output size (Donkeycar's ``IMAGE_W``, ``IMAGE_H``).
        fps: pacing for file sources, in frames per second (default: the file's own rate, else 20).
            ``0`` reads a file as fast as it decodes. Ignored for devices and streams.
        loop: at the end of a file, start again (True) or end (False).
        on_end: called once, from the reader thread, when a non-looping file ends.
        capture_size: ask a device for this ``(width, height)`` (many webcams default to 640x480).
        reopen_after: consecutive failed reads of a live source before it is released and opened again.
        clock: the time source for frame timestamps (seconds).
        backend: an OpenCV ``CAP_*`` API preference (default: OpenCV chooses).

    The constructor opens the source (raising :class:`CameraError` naming it if that fails); :meth:`start`
    starts the thread, or :meth:`run_forever` runs the same loop in the caller's thread.
    """

    def __init__(
        self,
        source: int | str,
        width: int = DEFAULT_IMAGE_W,
        height: int = DEFAULT_IMAGE_H,
        *,
        fps: float | None = None,
        loop: bool = True,
        on_end: Callable[[], Any] | None = None,
        capture_size: tuple[int, int] | None = None,
        reopen_after: int = 30,
        clock: Callable[[], float] = time.monotonic,
        backend: int | None = None,
    ) -> None:
        if isinstance(source, bool) or not isinstance(source, int | str):
            raise TypeError(f"CameraReader: source must be a device index or a path/URL, got {source!r}")
        for name, v in (("width", width), ("height", height)):
            if not (isinstance(v, int) and not isinstance(v, bool) and v > 0):
                raise ValueError(f"CameraReader({describe_source(source)}): {name} must be a positive int, got {v!r}")
        if fps is not None and not (isinstance(fps, int | float) and fps >= 0):
            raise ValueError(f"CameraReader({describe_source(source)}): fps must be >= 0 or None, got {fps!r}")
        if not (isinstance(reopen_after, int) and reopen_after > 0):
            raise ValueError(f"CameraReader: reopen_after must be a positive int, got {reopen_after!r}")
        self.source = source
        self.name = describe_source(source)
        self.width = width
        self.height = height
        self.loop = bool(loop)
        self.on_end = on_end
        self.capture_size = capture_size
        self.reopen_after = reopen_after
        self.clock = clock
        self.backend = backend
        self.is_file = _is_file_source(source)
        self.latest: Latest[np.ndarray] = Latest()
        self.frames = 0  # frames grabbed and published
        self.read_failures = 0
        self.reopens = 0
        self.loops = 0  # times a file wrapped around
        self.ended = False
        self.last_error: str | None = None
        self._stop = threading.Event()
        self._first = threading.Event()
        self._lock = threading.Lock()  # guards start()/close() against each other
        self._thread: threading.Thread | None = None
        self._running = False
        self._log = LogThrottle(1.0)
        self._cap = self._open()
        if self.is_file:
            if fps is None:
                file_fps = self._cap.get(cv2.CAP_PROP_FPS)
                fps = file_fps if file_fps and 0 < file_fps < 1000 else 20.0
            self.fps = float(fps)
        else:
            self.fps = 0.0

    # ------------------------------------------------------------------------------------------ opening
    def _open(self) -> Any:
        pattern = isinstance(self.source, str) and ("://" in self.source or "%" in self.source)
        if isinstance(self.source, str) and not pattern and not os.path.exists(self.source):
            raise CameraError(f"camera source {self.name}: no such file or device")
        cap = cv2.VideoCapture(self.source) if self.backend is None else cv2.VideoCapture(self.source, self.backend)
        if not cap.isOpened():
            cap.release()
            hint = " (is the camera connected and enabled, and is it free?)" if not self.is_file else ""
            raise CameraError(f"camera source {self.name}: OpenCV could not open it{hint}")
        if not self.is_file:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # a hint; the reader thread is what guarantees freshness
            if self.capture_size is not None:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.capture_size[0])
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.capture_size[1])
        return cap

    # ------------------------------------------------------------------------------------------ reading
    @property
    def sample(self) -> Sample[np.ndarray] | None:
        """The newest frame with its timestamp and sequence number (1, 2, ...), or None before the first."""
        return self.latest.sample

    def read_one(self) -> bool:
        """Grab, convert and publish one frame in the caller's thread. False on a failed read or at the end."""
        cap = self._cap
        if cap is None:
            return False
        ok, frame = cap.read()
        if ok and frame is not None:
            self.latest.publish(to_rgb(frame, self.width, self.height), self.clock())
            self.frames += 1
            self._first.set()
            return True
        if self.is_file:
            if self.loop and self.frames > 0:
                cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                self.loops += 1
                return self._read_after_rewind()
            self._end()
            return False
        self._failed("read returned no frame")
        return False

    def _read_after_rewind(self) -> bool:
        ok, frame = self._cap.read() if self._cap is not None else (False, None)
        if ok and frame is not None:
            self.latest.publish(to_rgb(frame, self.width, self.height), self.clock())
            self.frames += 1
            return True
        self._end()
        return False

    def _end(self) -> None:
        if not self.ended:
            self.ended = True
            logger.info("camera source %s: end of file after %d frames", self.name, self.frames)
            if self.on_end is not None:
                try:
                    self.on_end()
                except Exception:
                    logger.exception("camera source %s: on_end callback failed", self.name)

    def _failed(self, what: str) -> None:
        self.read_failures += 1
        self.last_error = what
        more = self._log.ready("read", time.monotonic())
        if more is not None:
            logger.warning("camera source %s: %s (%d failures so far)%s", self.name, what, self.read_failures, more)

    def wait_first_frame(self, timeout: float) -> Sample[np.ndarray]:
        """Block until a frame exists (at most ``timeout`` seconds); :class:`CameraError` names the source if not."""
        if not self._first.wait(timeout):
            detail = f"; last error: {self.last_error}" if self.last_error else ""
            why = "it ended" if self.ended else f"{self.read_failures} failed reads{detail}"
            raise CameraError(f"camera source {self.name}: no frame within {timeout:g} s ({why})")
        sample = self.latest.sample
        assert sample is not None
        return sample

    # ---------------------------------------------------------------------------------------- the thread
    def run_forever(self) -> None:
        """Grab until :meth:`stop` (or the end of a non-looping file), in the calling thread."""
        self._running = True
        failures_in_row = 0
        period = 1.0 / self.fps if self.fps > 0 else 0.0
        next_due = time.monotonic()
        try:
            while not self._stop.is_set() and not self.ended:
                if period:
                    delay = next_due - time.monotonic()
                    if delay > 0 and self._stop.wait(delay):
                        break
                    next_due = max(next_due + period, time.monotonic() - period)
                if self.read_one():
                    failures_in_row = 0
                    continue
                if self.ended:
                    break
                failures_in_row += 1
                if failures_in_row >= self.reopen_after:
                    failures_in_row = 0
                    self._reopen()
                elif self._stop.wait(0.01):  # a dead camera should not spin a core
                    break
        finally:
            self._running = False
            if self._stop.is_set():
                self._release()

    def _release(self) -> None:
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None

    def _reopen(self) -> None:
        with self._lock:
            if self._cap is not None:
                self._cap.release()
                self._cap = None
            try:
                self._cap = self._open()
                self.reopens += 1
                logger.warning("camera source %s: reopened after repeated read failures", self.name)
            except CameraError as exc:
                self._failed(str(exc))
        if self._cap is None:
            self._stop.wait(0.5)

    def start(self) -> None:
        """Start the reader thread (idempotent)."""
        with self._lock:
            if self._thread is not None or self._cap is None:
                return
            self._thread = threading.Thread(target=self.run_forever, name=f"camera:{self.name}", daemon=True)
            self._thread.start()

    @property
    def running(self) -> bool:
        """True while a reader loop (this reader's thread or :meth:`run_forever` elsewhere) is grabbing."""
        return self._running

    @property
    def started(self) -> bool:
        """True once :meth:`start` has started the reader thread."""
        return self._thread is not None

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and release the capture."""
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout)
        if not self._running:
            self._release()

    close = stop
