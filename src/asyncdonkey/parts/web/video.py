"""Camera video for any number of viewers at the cost of one JPEG encode per new frame.

Donkeycar's ``/video`` re-encodes the current image every 5 ms for each viewer, whether or not the camera has
produced a new one: 200 encodes a second per open page. :class:`FrameHub` instead

* takes the tick's image (``offer``, on the loop thread: an identity check and a reference, nothing else);
* encodes a frame only when it is new (a different array object from the last one) *and* someone watches,
  once, in its own worker thread, off the loop thread;
* hands that one JPEG to every viewer. A viewer always gets the newest JPEG: a slow one (a phone on a weak
  link) skips frames rather than queueing them, so its video stays live and the car's memory does not grow.

The stream is Donkeycar's: ``multipart/x-mixed-replace;boundary=--boundarydonotcross``, each part a
``--boundarydonotcross`` line, ``Content-type: image/jpeg`` and ``Content-length`` headers and the JPEG. The
boundary that ends a part is sent right after its JPEG (not when the next frame comes), so a browser shows a
frame as soon as it arrives, even when the camera stops.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
from typing import Any

import cv2
import numpy as np
from aiohttp import web

from ...ratelimit import LogThrottle

__all__ = ["BOUNDARY", "CONTENT_TYPE", "FrameHub", "encode_jpeg", "part_header"]

logger = logging.getLogger(__name__)

BOUNDARY = b"--boundarydonotcross"
CONTENT_TYPE = "multipart/x-mixed-replace;boundary=--boundarydonotcross"


def part_header(length: int) -> bytes:
    """The headers of one multipart part carrying a JPEG of ``length`` bytes (after its boundary line)."""
    return b"Content-type: image/jpeg\r\nContent-length: %d\r\n\r\n" % length


def encode_jpeg(frame: np.ndarray, quality: int) -> bytes:
    """A camera image (``HxWx3`` RGB, ``HxWx1`` or ``HxW`` grey, uint8) as JPEG bytes."""
    arr = np.asarray(frame)
    if arr.dtype != np.uint8:
        raise TypeError(f"video: camera images must be uint8, got {arr.dtype}")
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    elif not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 1)):
        raise ValueError(f"video: camera images must be HxWx3 (RGB) or grey, got shape {arr.shape}")
    ok, buf = cv2.imencode(".jpg", arr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError(f"video: OpenCV could not encode an image of shape {arr.shape}")
    return buf.tobytes()


class FrameHub:
    """The newest camera frame as one shared JPEG (see the module docstring).

    Args:
        quality: JPEG quality (1-100).
        placeholder_size: ``(width, height)`` of the grey image shown before the first frame.

    Counters: ``offered`` (new frames seen), ``encodes``, ``encode_errors``, ``viewers`` (open streams),
    ``parts_sent`` (JPEGs written to viewers, all viewers together).
    """

    def __init__(self, quality: int = 80, placeholder_size: tuple[int, int] = (160, 120)) -> None:
        if not 1 <= int(quality) <= 100:
            raise ValueError(f"FrameHub: JPEG quality must be 1..100, got {quality!r}")
        self.quality = int(quality)
        w, h = placeholder_size
        self.jpeg = encode_jpeg(np.full((h, w, 3), 96, np.uint8), self.quality)
        self.seq = 0  # bumps with every JPEG published; 0 is the placeholder
        self.offered = 0
        self.encodes = 0
        self.encode_errors = 0
        self.viewers = 0
        self.parts_sent = 0
        self.closed = False
        self._frame: Any = None  # newest frame offered
        self._encoded: Any = None  # the frame self.jpeg was made from
        self._wake: asyncio.Event | None = None
        self._cond: asyncio.Condition | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._log = LogThrottle(5.0)

    # ------------------------------------------------------------------------------ producer side
    def offer(self, frame: Any) -> None:
        """The tick's image. Cheap: a new frame is only remembered, and flagged for encoding if anyone watches."""
        if frame is None or frame is self._frame:
            return
        self._frame = frame
        self.offered += 1
        if self.viewers and self._wake is not None:
            self._wake.set()

    async def run(self) -> None:
        """Encode new frames while anyone watches, until :meth:`close`. Runs as a task on the drive loop."""
        loop = asyncio.get_running_loop()
        self.closed = False
        wake = self._wake = asyncio.Event()  # made here: each drive may run on a new event loop
        self._cond = asyncio.Condition()
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="asyncdonkey-web-jpeg")
        try:
            while not self.closed:
                await wake.wait()
                wake.clear()
                frame = self._frame
                if self.closed or frame is None or frame is self._encoded or not self.viewers:
                    continue
                try:
                    jpeg = await loop.run_in_executor(self._executor, encode_jpeg, frame, self.quality)
                except (TypeError, ValueError) as exc:
                    self.encode_errors += 1
                    self._encoded = frame  # do not retry the same bad frame
                    held = self._log.ready("encode", loop.time(), "frames not shown")
                    if held is not None:
                        logger.error("web video: a frame could not be shown%s: %s", held, exc)
                    continue
                self._encoded = frame
                self.jpeg = jpeg
                self.seq += 1
                self.encodes += 1
                async with self._cond:
                    self._cond.notify_all()
        finally:
            self._executor.shutdown(wait=False)

    async def close(self) -> None:
        """End every stream and the encoder."""
        self.closed = True
        if self._wake is not None:
            self._wake.set()
        if self._cond is not None:
            async with self._cond:
                self._cond.notify_all()

    # ------------------------------------------------------------------------------ viewer side
    async def next_after(self, seq: int) -> tuple[int, bytes] | None:
        """The newest JPEG once it is newer than ``seq`` (``None`` when the hub closes)."""
        if self.seq > seq:
            return self.seq, self.jpeg
        cond = self._cond
        if cond is None:
            raise RuntimeError("FrameHub: run() must be running before viewers wait for frames")
        async with cond:
            await cond.wait_for(lambda: self.seq > seq or self.closed)
        return None if self.closed else (self.seq, self.jpeg)

    async def stream(self, request: web.Request) -> web.StreamResponse:
        """Serve ``/video``: Donkeycar's MJPEG stream of the newest frames to one viewer."""
        resp = web.StreamResponse(headers={"Content-Type": CONTENT_TYPE, "Cache-Control": "no-store"})
        await resp.prepare(request)
        self.viewers += 1
        if self._wake is not None and self._frame is not None and self._frame is not self._encoded:
            self._wake.set()  # first viewer after a quiet spell: encode the frame we have now
        seq = -1
        try:
            await resp.write(BOUNDARY + b"\n")
            while not self.closed:
                got = await self.next_after(seq)
                if got is None:
                    break
                seq, jpeg = got
                await resp.write(part_header(len(jpeg)) + jpeg + b"\r\n" + BOUNDARY + b"\n")
                self.parts_sent += 1
        except (ConnectionResetError, ConnectionError):
            pass  # the viewer went away
        finally:
            self.viewers -= 1
        return resp
