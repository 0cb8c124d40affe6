"""Turning a channel's value into what the tub stores, per Tub v2 type (runs on the writer thread).

Each converter takes the value the part received and returns a JSON-ready value, or, for the image types,
the encoded file bytes. It raises ``TypeError``/``ValueError`` saying what it expected; the writer then omits
that one value from the record (counted and logged with the channel's name) and keeps the rest, so one bad
value never costs a record. ``None`` never reaches a converter: like Donkeycar, a ``None`` value is left out
of the record (e.g. no camera frame yet).

Differences from Donkeycar's conversions, on purpose:

* ``float``/``int`` refuse strings, and non-finite floats (``NaN``, ``inf``) are refused rather than written:
  Donkeycar writes catalogs with ``allow_nan=False``, so a ``NaN`` raised inside the drive loop there.
* ``image_array`` must be ``uint8`` (Donkeycar's ``np.uint8(value)`` silently wraps a float image to garbage);
  it is encoded with OpenCV (``cv2.imencode``) after converting RGB to BGR, at JPEG quality 75 like PIL's
  default that Donkeycar uses.
* ``gray16_array`` works (Donkeycar 5.3 passes ``ext=`` to a function whose parameter is ``extension`` and so
  raises on every gray16 record); it is stored as a 16-bit PNG.
* ``list``/``vector``/``nparray`` accept numpy arrays, numpy scalars and sequences alike.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

__all__ = ["json_default", "make_converter"]

Converter = Callable[[Any], Any]


def _float(v: Any) -> float:
    if isinstance(v, str | bytes):
        raise TypeError(f"expected a number, got {type(v).__name__} {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"expected a finite number, got {f!r}")
    return f


def _int(v: Any) -> int:
    if isinstance(v, str | bytes):
        raise TypeError(f"expected an integer, got {type(v).__name__} {v!r}")
    try:
        return int(v)
    except OverflowError:
        raise ValueError(f"expected a finite number, got {v!r}") from None


def _str(v: Any) -> str:
    if not isinstance(v, str):
        raise TypeError(f"expected str, got {type(v).__name__} {v!r}")
    return v


def _bool(v: Any) -> bool:
    return bool(v)


def _nparray(v: Any) -> list[Any]:
    a = np.asarray(v)
    if a.dtype.kind not in "biuf":
        raise TypeError(f"expected a numeric array, got dtype {a.dtype}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ValueError("expected finite values, the array holds NaN or inf")
    return a.tolist()


def _list(v: Any) -> list[Any]:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, str | bytes) or not hasattr(v, "__iter__"):
        raise TypeError(f"expected a list or sequence, got {type(v).__name__}")
    return list(v)


def _image_jpeg(quality: int) -> Converter:
    params = [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)]
    rgb2bgr = cv2.COLOR_RGB2BGR
    cvt = cv2.cvtColor
    imencode = cv2.imencode

    def encode(v: Any) -> bytes:
        if isinstance(v, bytes | bytearray | memoryview) and bytes(v[:2]) == b"\xff\xd8":
            return bytes(v)  # already a JPEG (a conversion copying frames between formats): kept as is
        if not isinstance(v, np.ndarray) or v.dtype != np.uint8:
            what = f"dtype {v.dtype}" if isinstance(v, np.ndarray) else type(v).__name__
            raise TypeError(f"expected a uint8 numpy image (HxWx3 RGB or HxW grey), got {what}")
        if v.ndim == 3 and v.shape[2] == 3:
            img = cvt(v, rgb2bgr)
        elif v.ndim == 2 or (v.ndim == 3 and v.shape[2] == 1):
            img = v
        else:
            raise ValueError(f"expected an HxWx3 RGB or HxW grey image, got shape {v.shape}")
        ok, buf = imencode(".jpg", img, params)
        if not ok:  # pragma: no cover - OpenCV fails only on empty images
            raise ValueError(f"JPEG encoding failed for shape {v.shape}")
        return buf.tobytes()

    return encode


def _gray16_png(v: Any) -> bytes:
    if not isinstance(v, np.ndarray) or v.dtype not in (np.uint16, np.uint8):
        what = f"dtype {v.dtype}" if isinstance(v, np.ndarray) else type(v).__name__
        raise TypeError(f"expected a uint16 numpy image (HxW), got {what}")
    img = v[:, :, 0] if v.ndim == 3 and v.shape[2] == 1 else v
    if img.ndim != 2:
        raise ValueError(f"expected an HxW single-channel image, got shape {v.shape}")
    ok, buf = cv2.imencode(".png", img.astype(np.uint16, copy=False))
    if not ok:  # pragma: no cover
        raise ValueError(f"PNG encoding failed for shape {v.shape}")
    return buf.tobytes()


def make_converter(type_name: str, *, jpeg_quality: int = 75) -> Converter:
    """The converter for Tub v2 type ``type_name`` (checked against :data:`~.format.TYPES` by the caller)."""
    if type_name == "image_array":
        return _image_jpeg(jpeg_quality)
    table: dict[str, Converter] = {
        "float": _float,
        "int": _int,
        "str": _str,
        "boolean": _bool,
        "nparray": _nparray,
        "list": _list,
        "vector": _list,
        "gray16_array": _gray16_png,
    }
    return table[type_name]


def json_default(o: Any) -> Any:
    """``json.dumps(default=...)``: numpy scalars and arrays inside lists become plain Python values."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple | set | frozenset):
        return list(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")
