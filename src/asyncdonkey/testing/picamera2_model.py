"""A model of the part of ``picamera2`` (libcamera on a Raspberry Pi) that :mod:`asyncdonkey.hw.picamera` uses.

``picamera2`` only runs on a Pi with the libcamera bindings from apt, so the driver is tested against this
model, which behaves like the library as the driver sees it (picamera2 0.3.x, read from its source):

* ``Picamera2(camera_num)`` opens a camera. With no camera detected (a loose ribbon, a camera disabled in
  ``config.txt``) the real constructor fails in ``global_camera_info()[camera_num]`` with ``IndexError: list index
  out of range``; a camera another process (or another ``Picamera2``) holds fails to be acquired, reported as
  ``RuntimeError("Camera __init__ sequence did not complete.")``. The model raises the same.
* ``create_video_configuration(main=..., buffer_count=..., controls=..., queue=True)`` returns the dict picamera2
  builds: ``main`` defaults to ``XBGR8888`` at 1280x720 and is aligned to even sizes, ``controls`` get
  ``FrameDurationLimits`` (33333, 33333) unless given. ``configure()`` checks the format and fills in ``stride``.
* Byte order: picamera2's format names are DRM fourccs, which name the channels of a little-endian word. So
  ``"RGB888"`` arrays are **B, G, R** in memory and ``"BGR888"`` arrays are R, G, B; ``XRGB8888`` is B, G, R, X and
  ``XBGR8888`` is R, G, B, X. The model's :attr:`scene` is the true picture (RGB); ``make_array`` returns it in the
  byte order of the configured format, so a driver that gets the order wrong sees red and blue swapped.
* Buffers are few. ``start()`` queues ``buffer_count`` requests to the camera. Each frame that completes takes
  one queued request; with none queued the frame is dropped (the sensor keeps running). With ``queue=True`` (and
  more than one buffer) picamera2 keeps the newest completed request ready and recycles older ones;
  ``capture_request()`` hands one out and it returns to the camera only on ``request.release()``. A driver that
  forgets to release runs the camera dry: the next ``capture_request`` blocks forever, or with ``wait=<seconds>``
  raises ``TimeoutError`` (picamera2 waits on a ``concurrent.futures.Future``).
* A capture that timed out leaves its job queued in picamera2: it takes the next frame that arrives and nobody
  ever releases that request, unless ``cancel_all_and_flush()`` is called (picamera2's documented tidy-up "after
  an operation has unexpectedly timed out"). The model does the same, so a driver that skips it leaks a buffer per
  timeout. ``cancel_all_and_flush()`` also makes a capture still waiting raise ``concurrent.futures.CancelledError``.
* Metadata: ``SensorTimestamp`` is the start of the exposure of the first row, in nanoseconds on
  ``CLOCK_BOOTTIME`` (libcamera's control reference); ``ExposureTime`` and ``FrameDuration`` in microseconds.
  A request is complete one frame duration after its ``SensorTimestamp`` (plus ``isp_latency_s``).
* After ``release()``, ``make_array`` raises ``RuntimeError("Stream 'main' is not defined")`` (the request's config
  is dropped), as in picamera2.

Faults: :meth:`Picamera2Model.stall` stops frames (a capture then blocks, as when the ribbon works loose
mid-drive: libcamera completes no request, or completes them with errors that picamera2 discards);
:meth:`~Picamera2Model.resume` restarts them; :meth:`~Picamera2Model.unplug` stops frames and makes the next
``Picamera2()`` fail as with no camera.

**Time.** ``clock="real"``: frames come at their real times on ``CLOCK_BOOTTIME`` and captures wait in real time.
``clock="simulated"`` (the default): the model keeps its own nanosecond clock, which moves only while a capture
waits, straight to the moment the awaited frame completes (or by the whole timeout): runs are exact and instant,
and a driver reading :meth:`Picamera2Model.clock_ns` as its sensor clock sees every frame exactly as old as the
model made it. A capture with no timeout that would wait forever raises :class:`Picamera2ModelHang` instead.

Installing it (see ``tests/hw/test_picamera.py``)::

    rig = Picamera2Model(fps=20)
    with rig.installed():            # sys.modules["picamera2"] is the model's module meanwhile
        cam = PiCameraDriver(160, 120, sensor_clock_ns=rig.clock_ns)

or pass ``picamera2=rig.module`` to the driver or the part.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import sys
import threading
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from ..errors import AsyncdonkeyError

__all__ = ["Picamera2Model", "Picamera2ModelHang"]

_FORMATS = {"RGB888": 3, "BGR888": 3, "XRGB8888": 4, "XBGR8888": 4}


class Picamera2ModelHang(AsyncdonkeyError, AssertionError):
    """A call that would block forever on the real library (``capture_request()`` without a timeout)."""


def _boottime_ns() -> int:
    return time.clock_gettime_ns(time.CLOCK_BOOTTIME)


def _default_scene(k: int, width: int, height: int) -> np.ndarray:
    from .camera_models import make_frame_bgr

    return np.ascontiguousarray(make_frame_bgr(k, width, height)[..., ::-1])


def _in_format(rgb: np.ndarray, fmt: str) -> np.ndarray:
    """The true RGB picture laid out in memory as picamera2's ``fmt`` is."""
    if fmt == "BGR888":
        return rgb.copy()
    if fmt == "RGB888":
        return np.ascontiguousarray(rgb[..., ::-1])
    pad = np.full((*rgb.shape[:2], 1), 255, np.uint8)
    if fmt == "XBGR8888":
        return np.concatenate([rgb, pad], axis=2)
    return np.concatenate([rgb[..., ::-1], pad], axis=2)  # XRGB8888


class Picamera2Model:
    """The camera hardware, libcamera and picamera2 together: see the module docstring.

    Args:
        fps: the sensor's rate until ``FrameDurationLimits`` sets it (picamera2's video default is 30).
        scene: ``scene(k, width, height) -> RGB uint8 (height, width, 3)``, what frame ``k`` shows. The default
            draws :func:`~asyncdonkey.testing.camera_models.make_frame_bgr`'s numbered frames (RGB).
        video: a video file whose frames are shown in turn (looping), instead of ``scene``.
        cameras: how many cameras libcamera detects.
        clock: ``"simulated"`` or ``"real"`` (see the module docstring).
        exposure_us: the ``ExposureTime`` reported.
        isp_latency_s: extra time between the end of a frame and its request completing.
        model_name: the sensor model reported in ``camera_properties``.
        suspended_s: with ``clock="real"``, how far ``CLOCK_BOOTTIME`` is ahead of ``CLOCK_MONOTONIC`` (the time
            a machine spent suspended), to check that a driver does not take one clock for the other.
    """

    def __init__(
        self,
        *,
        fps: float = 30.0,
        scene: Callable[[int, int, int], np.ndarray] | None = None,
        video: str | None = None,
        cameras: int = 1,
        clock: str = "simulated",
        exposure_us: int = 10000,
        isp_latency_s: float = 0.0,
        model_name: str = "imx219",
        suspended_s: float = 0.0,
    ) -> None:
        if clock not in ("simulated", "real"):
            raise ValueError(f"Picamera2Model: clock must be 'simulated' or 'real', got {clock!r}")
        self.simulated = clock == "simulated"
        self.default_period_ns = round(1e9 / fps)
        self.scene = scene or _default_scene
        if video is not None:
            self.scene = _video_scene(video)
        self.cameras = cameras
        self.exposure_us = exposure_us
        self.isp_latency_ns = round(isp_latency_s * 1e9)
        self.model_name = model_name
        self.suspended_ns = round(suspended_s * 1e9)
        self._now_ns = 10**12  # the simulated clock: boot was a while ago
        self._cond = threading.Condition()
        self._held_by: set[int] = set()  # camera numbers some open Picamera2 has acquired
        self.unplugged = False
        self.stalled = False
        self.frames_delivered = 0  # frames that completed a request
        self.frames_dropped = 0  # frames that found no request queued
        self.opened = 0  # Picamera2 instances created successfully
        self.cameras_open: list[Any] = []
        self.module = self._make_module()

    # ------------------------------------------------------------------------------------------ time
    def clock_ns(self) -> int:
        """The sensor clock: ``CLOCK_BOOTTIME`` nanoseconds, or the simulated clock."""
        if self.simulated:
            with self._cond:
                return self._now_ns
        return _boottime_ns() + self.suspended_ns

    def _now(self) -> int:  # with the condition held
        return self._now_ns if self.simulated else _boottime_ns() + self.suspended_ns

    # ------------------------------------------------------------------------------------------ faults
    def stall(self) -> None:
        """Frames stop coming (captures block) until :meth:`resume`."""
        with self._cond:
            self.stalled = True
            for cam in self.cameras_open:
                cam._stall_at(self._now())
            self._cond.notify_all()

    def resume(self) -> None:
        """Frames come again, from the next frame time on."""
        with self._cond:
            self.stalled = False
            for cam in self.cameras_open:
                cam._resume_at(self._now())
            self._cond.notify_all()

    def unplug(self) -> None:
        """The camera is gone: no more frames, and a new ``Picamera2()`` fails as with no camera detected."""
        with self._cond:
            self.unplugged = True
        self.stall()

    # ------------------------------------------------------------------------------------------ module
    def _make_module(self) -> types.ModuleType:
        rig = self
        module = types.ModuleType("picamera2", "Model of picamera2 (asyncdonkey.testing.picamera2_model)")

        class Picamera2(_ModelCamera):
            _rig = rig

            @staticmethod
            def global_camera_info() -> list[dict[str, Any]]:
                if rig.unplugged:
                    return []
                return [
                    {"Model": rig.model_name, "Location": 2, "Rotation": 0, "Id": f"/model/{i}", "Num": i}
                    for i in range(rig.cameras)
                ]

        module.Picamera2 = Picamera2  # type: ignore[attr-defined]
        module.__file__ = __file__
        return module

    @contextlib.contextmanager
    def installed(self) -> Iterator[types.ModuleType]:
        """Make ``import picamera2`` give this model's module for the duration of the block."""
        saved = sys.modules.get("picamera2")
        sys.modules["picamera2"] = self.module
        try:
            yield self.module
        finally:
            if saved is None:
                sys.modules.pop("picamera2", None)
            else:
                sys.modules["picamera2"] = saved


def _video_scene(path: str) -> Callable[[int, int, int], np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(path)
    frames = []
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    finally:
        cap.release()
    if not frames:
        raise ValueError(f"Picamera2Model: no frames could be read from the video {path!r}")

    def scene(k: int, width: int, height: int) -> np.ndarray:
        f = frames[k % len(frames)]
        if f.shape[:2] != (height, width):
            f = cv2.resize(f, (width, height), interpolation=cv2.INTER_AREA)
        return f

    return scene


class ModelRequest:
    """picamera2's ``CompletedRequest``: one frame's buffer and metadata, held until :meth:`release`."""

    def __init__(self, cam: _ModelCamera, frame: int, ts_ns: int, period_ns: int) -> None:
        self._cam = cam
        self.frame = frame
        self.ref_count = 1
        self.config: dict[str, Any] = dict(cam.camera_config)
        self._stop_count = cam.stop_count
        self._metadata = {
            "SensorTimestamp": ts_ns,
            "ExposureTime": min(cam._rig.exposure_us, period_ns // 1000),
            "FrameDuration": period_ns // 1000,
            "AnalogueGain": 1.0,
            "DigitalGain": 1.0,
        }
        self._released = False

    def acquire(self) -> None:
        with self._cam._rig._cond:
            if self.ref_count == 0:
                raise RuntimeError("CompletedRequest: acquiring lock with ref_count 0")
            self.ref_count += 1

    def release(self) -> None:
        cam = self._cam
        with cam._rig._cond:
            self.ref_count -= 1
            if self.ref_count < 0:
                raise RuntimeError("CompletedRequest: lock now has negative ref_count")
            if self.ref_count == 0:
                self._released = True
                self.config = {}
                cam.app_held -= 1
                if cam.started and cam.stop_count == self._stop_count:
                    cam.queued += 1  # back to the camera
                    cam._rig._cond.notify_all()

    def get_metadata(self) -> dict[str, Any]:
        assert not self._released  # picamera2: `assert self.request is not None`
        return dict(self._metadata)

    def make_array(self, name: str) -> np.ndarray:
        config = self.config.get(name)
        if config is None:
            raise RuntimeError(f"Stream {name!r} is not defined")
        w, h = config["size"]
        rgb = self._cam._rig.scene(self.frame, w, h)
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"Picamera2Model: scene gave {rgb.shape} {rgb.dtype}, expected ({h}, {w}, 3) uint8")
        return _in_format(rgb, config["format"])


class _ModelCamera:
    """picamera2's ``Picamera2`` class, the calls the driver makes (bound to a rig by ``Picamera2Model``)."""

    _rig: Picamera2Model

    def __init__(self, camera_num: int = 0, verbose_console: Any = None, tuning: Any = None, allocator: Any = None):
        rig = self._rig
        self.is_open = False
        self.started = False
        info = self.global_camera_info()  # type: ignore[attr-defined]
        camera_num = info[camera_num]["Num"]  # IndexError: list index out of range, as picamera2 0.3.x
        with rig._cond:
            if camera_num in rig._held_by:
                raise RuntimeError("Camera __init__ sequence did not complete.")
            rig._held_by.add(camera_num)
            rig.cameras_open.append(self)
            rig.opened += 1
        self.camera_idx = camera_num
        self.camera = object()
        self.is_open = True
        self.camera_config: dict[str, Any] = {}
        self.camera_properties = {"Model": rig.model_name, "PixelArraySize": (3280, 2464)}
        self.sensor_resolution = (3280, 2464)
        self.stop_count = 0
        self.queued = 0  # requests queued to the camera
        self.app_held = 0  # requests handed out and not released
        self.orphan_jobs = 0  # timed-out captures still queued in picamera2
        self._ready: list[ModelRequest] = []  # completed requests picamera2 holds (at most max_queue_len)
        self._max_queue_len = 1
        self._period_ns = rig.default_period_ns
        self._next_ts = 0  # SensorTimestamp of the next frame to be exposed
        self._frame = 0  # number of that frame
        self._stalled_since: int | None = None
        self._cancel_gen = 0

    # --------------------------------------------------------------------------------- configuration
    def create_video_configuration(
        self,
        main: dict[str, Any] | None = None,
        lores: Any = None,
        raw: Any = None,
        transform: Any = None,
        colour_space: Any = None,
        buffer_count: int = 6,
        controls: dict[str, Any] | None = None,
        display: str | None = "main",
        encode: str | None = "main",
        queue: bool = True,
        sensor: Any = None,
        use_case: str = "video",
    ) -> dict[str, Any]:
        if self.camera is None:
            raise RuntimeError("Camera not opened")
        stream = {"format": "XBGR8888", "size": (1280, 720), "preserve_ar": True} | dict(main or {})
        w, h = stream["size"]
        stream["size"] = (w - w % 2, h - h % 2)  # align_stream(optimal=False)
        ctrls = {"NoiseReductionMode": 1, "FrameDurationLimits": (33333, 33333)} | dict(controls or {})
        return {
            "use_case": use_case,
            "transform": transform,
            "colour_space": colour_space,
            "buffer_count": buffer_count,
            "queue": queue,
            "main": stream,
            "lores": lores,
            "raw": raw,
            "controls": ctrls,
            "sensor": sensor,
            "display": display,
            "encode": encode,
        }

    def configure(self, camera_config: dict[str, Any] | None = None) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        if not isinstance(camera_config, dict):
            raise TypeError("Invalid type for `camera_config` given")
        main = dict(camera_config["main"])
        fmt = main.get("format")
        if fmt not in _FORMATS:
            raise RuntimeError(f"Bad format {fmt} in stream main")
        w, h = main["size"]
        if w % 2 or h % 2:
            raise RuntimeError("width and height should be even")
        main["stride"] = w * _FORMATS[fmt]
        config = dict(camera_config)
        config["main"] = main
        self.camera_config = config
        self._max_queue_len = 1 if config.get("queue", True) and config["buffer_count"] > 1 else 0
        self.set_controls(config.get("controls") or {})

    def set_controls(self, controls: dict[str, Any]) -> None:
        limits = controls.get("FrameDurationLimits")
        if limits is not None:
            lo, hi = limits
            if not (0 < lo <= hi):
                raise ValueError(f"FrameDurationLimits must be (min, max) microseconds, got {limits!r}")
            with self._rig._cond:
                self._period_ns = int(lo) * 1000  # the sensor runs as fast as the limits allow

    # -------------------------------------------------------------------------------- start and stop
    def start(self, config: Any = None, show_preview: Any = False) -> None:
        if config is not None:
            self.configure(config)
        if not self.camera_config:
            raise RuntimeError("Camera has not been configured")
        rig = self._rig
        with rig._cond:
            if self.started:
                return
            self.started = True
            self.queued = self.camera_config["buffer_count"]
            self._ready = []
            self._next_ts = rig._now()  # the first exposure starts now
            self._stalled_since = rig._now() if rig.stalled else None
            rig._cond.notify_all()

    def stop(self) -> None:
        rig = self._rig
        with rig._cond:
            if not self.started:
                return
            self.started = False
            self.stop_count += 1
            self._ready = []
            self.queued = 0
            rig._cond.notify_all()

    def close(self) -> None:
        if not self.is_open:
            return
        self.stop()
        rig = self._rig
        with rig._cond:
            rig._held_by.discard(self.camera_idx)
            if self in rig.cameras_open:
                rig.cameras_open.remove(self)
            self.is_open = False
            self.camera = None
            self.camera_config = {}

    def cancel_all_and_flush(self) -> None:
        rig = self._rig
        with rig._cond:
            self.orphan_jobs = 0
            self._cancel_gen += 1
            rig._cond.notify_all()

    # ---------------------------------------------------------------------------------------- frames
    def _stall_at(self, now: int) -> None:
        if self._stalled_since is None:
            self._stalled_since = now

    def _resume_at(self, now: int) -> None:
        if self._stalled_since is not None:
            self._stalled_since = None
            if self._next_ts < now:  # the sensor picks up on its own frame grid
                skipped = -(-(now - self._next_ts) // self._period_ns)
                self._frame += skipped
                self._next_ts += skipped * self._period_ns

    def _due(self) -> int:
        """When the next frame's request completes."""
        return self._next_ts + self._period_ns + self._rig.isp_latency_ns

    def _advance(self, now: int, waiting: bool) -> ModelRequest | None:
        """Complete every frame due by ``now``. With ``waiting``, stop at and return the first one a capture
        that is waiting takes (picamera2 runs its jobs as each frame arrives)."""
        rig = self._rig
        while self.started and self._stalled_since is None and self._due() <= now:
            k, ts = self._frame, self._next_ts
            self._frame += 1
            self._next_ts += self._period_ns
            if self.queued == 0:
                rig.frames_dropped += 1
                continue
            self.queued -= 1
            rig.frames_delivered += 1
            req = ModelRequest(self, k, ts, self._period_ns)
            if self.orphan_jobs:  # a timed-out capture's job takes it, and nobody will release it
                self.orphan_jobs -= 1
                self.app_held += 1
                continue
            if waiting:
                self.app_held += 1
                return req
            self._ready.append(req)
            while len(self._ready) > self._max_queue_len:
                self._ready.pop(0)
                self.queued += 1  # recycled to the camera
        return None

    def capture_request(self, wait: Any = None, signal_function: Any = None, flush: Any = None) -> ModelRequest:
        if signal_function is not None or wait is False or flush is not None:
            raise NotImplementedError("Picamera2Model: only blocking capture_request(wait=None|True|seconds)")
        timeout = None if wait is None or wait is True else float(wait)
        rig = self._rig
        with rig._cond:
            now = rig._now()
            self._advance(now, waiting=False)
            if self._ready:
                req = self._ready.pop(0)
                self.app_held += 1
                return req
            deadline = None if timeout is None else now + round(timeout * 1e9)
            gen = self._cancel_gen
            while True:
                now = rig._now()
                req = self._advance(now, waiting=True)
                if req is not None:
                    return req
                if self._cancel_gen != gen:
                    raise concurrent.futures.CancelledError()
                can_come = self.started and self._stalled_since is None and self.queued > 0
                if rig.simulated:
                    if can_come and (deadline is None or self._due() <= deadline):
                        rig._now_ns = max(now, self._due())
                        continue
                    if deadline is None:
                        why = "the camera is stalled" if self._stalled_since is not None else "no request is queued"
                        raise Picamera2ModelHang(f"capture_request() without a timeout would block forever: {why}")
                    rig._now_ns = deadline
                    self.orphan_jobs += 1
                    raise concurrent.futures.TimeoutError()
                if deadline is not None and now >= deadline:
                    self.orphan_jobs += 1
                    raise concurrent.futures.TimeoutError()
                wake = self._due() if can_come else None
                if deadline is not None:
                    wake = deadline if wake is None else min(wake, deadline)
                rig._cond.wait(None if wake is None else max(wake - now, 0) / 1e9 + 1e-4)

    def __enter__(self) -> _ModelCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
