"""Synthetic camera sources: real MJPG ``.avi`` files and image folders whose frames say which frame they are.

The camera code is tested through OpenCV's real capture path (``cv2.VideoCapture`` decoding an MJPG file), not
through a fake ``read()``. To tell *which* frame a consumer was served, each frame carries its number as a row
of black/white bands (one bit per band, most significant first) across the top half; the bands are wide and
flat so JPEG compression and a 2x downscale leave them readable. The bottom half is a solid colour (``color``,
BGR) or, by default, a bar that moves with the frame number so the picture visibly changes.

:func:`frame_number` reads the number back from an RGB frame of any size.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

__all__ = ["FRAME_BITS", "frame_number", "make_frame_bgr", "write_image_folder", "write_test_video"]

#: bits of frame number encoded in each frame (frames 0..1023; numbers wrap beyond)
FRAME_BITS = 10


def make_frame_bgr(
    index: int, width: int = 320, height: int = 240, color: tuple[int, int, int] | None = None
) -> np.ndarray:
    """One synthetic BGR frame: the number ``index`` in bands on top, ``color`` or a moving bar below."""
    frame = np.zeros((height, width, 3), np.uint8)
    band = width // FRAME_BITS
    code = index % (1 << FRAME_BITS)
    for bit in range(FRAME_BITS):
        if code >> (FRAME_BITS - 1 - bit) & 1:
            frame[: height // 2, bit * band : (bit + 1) * band] = 255
    lower = frame[height // 2 :]
    if color is not None:
        lower[:] = color
    else:
        lower[:] = (40, 40, 40)
        bar = max(width // 16, 2)
        x = (index * 7) % (width - bar)
        lower[:, x : x + bar] = (0, 200, 255)
    return frame


def frame_number(image_rgb: np.ndarray) -> int:
    """The frame number encoded by :func:`make_frame_bgr`, read from an RGB (or BGR) frame of any size."""
    h, w = image_rgb.shape[:2]
    band = w / FRAME_BITS
    top = image_rgb[: h // 2].astype(np.float32).mean(axis=2)
    value = 0
    for bit in range(FRAME_BITS):
        lo = int(bit * band + band * 0.25)
        hi = max(int((bit + 1) * band - band * 0.25), lo + 1)
        mean = float(top[h // 8 : h // 2 - h // 8, lo:hi].mean())
        value = (value << 1) | (1 if mean > 127 else 0)
    return value


def write_test_video(
    path: str | os.PathLike[str],
    n_frames: int = 60,
    *,
    width: int = 320,
    height: int = 240,
    fps: float = 20.0,
    color: tuple[int, int, int] | None = None,
    frames: Sequence[np.ndarray] | None = None,
) -> Path:
    """Write an MJPG ``.avi`` with OpenCV: ``n_frames`` numbered frames (or the given BGR ``frames``).

    Returns the path. Raises ``RuntimeError`` naming the file if OpenCV cannot write it.
    """
    p = Path(path)
    writer = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"MJPG"), float(fps), (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"write_test_video: OpenCV cannot write an MJPG video to {str(p)!r}")
    try:
        source = frames if frames is not None else (make_frame_bgr(i, width, height, color) for i in range(n_frames))
        for f in source:
            if f.shape[:2] != (height, width):
                raise ValueError(f"write_test_video({p}): frame of shape {f.shape}, expected ({height}, {width}, 3)")
            writer.write(f)
    finally:
        writer.release()
    return p


def write_image_folder(
    folder: str | os.PathLike[str],
    n_images: int = 10,
    *,
    width: int = 320,
    height: int = 240,
    name: str = "{index}_cam_image_array_.jpg",
    color: tuple[int, int, int] | None = None,
) -> list[Path]:
    """Write numbered JPEG frames named like a tub's ``images/`` (``0_cam_image_array_.jpg``, ...)."""
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n_images):
        p = d / name.format(index=i)
        if not cv2.imwrite(str(p), make_frame_bgr(i, width, height, color)):
            raise RuntimeError(f"write_image_folder: OpenCV could not write {str(p)!r}")
        paths.append(p)
    return paths
