"""How Memory values travel over Zenoh: the payload, Zenoh's encoding field, and the age attachment.

Everything here is readable by any Zenoh client (C, C++, Rust, ROS 2 through ``zenoh-bridge-ros2dds``) without
Python or numpy on the other side:

================================ ============================================== ==================================
value                            encoding (Zenoh's encoding field)              payload
================================ ============================================== ==================================
numpy array                      ``application/octet-stream;ndarray;dtype=<f4   the array's bytes, C order; dtype is
                                 ;shape=120,160,3``                             numpy's array-interface type string
                                                                                (byte order, kind, item size)
image sent as JPEG               ``image/jpeg``                                 a baseline JPEG; decoded to an RGB
                                                                                ``uint8`` array (Donkeycar's
                                                                                ``cam/image_array`` layout)
number, bool, str, None, small   ``application/json``                           UTF-8 JSON
list or dict
bytes                            ``application/octet-stream``                   as is
================================ ============================================== ==================================

A **command group** (``ZenohPublisher(..., group="pilot/command")``) sends several channels as one sample on
one key, so a receiver applies them together with one origin (a steering and a throttle that never arrive
half-new): encoding ``application/json;group;v=1``, payload a UTF-8 JSON object with exactly the group's
channels, e.g. ``{"pilot/angle":-0.12,"pilot/throttle":0.45}``. ``v`` is the version of this layout; a receiver
refuses a version it does not know.

The **attachment** of every sample is 24 bytes, little-endian: ``float64`` age in seconds of the sensing behind
the value at the moment it was sent, ``uint64`` sequence number of the sample on its key (1, 2, ...), and
``uint64`` source: a random number drawn by each publisher when it starts, so a receiver can tell a restarted
sender (whose numbering starts over) from late samples.
The age, not a timestamp, crosses the network because the two machines' clocks are not synchronised; the
receiver adds the transit it measured (see :mod:`.link`). A receiver refuses a sample whose age is not a finite
number in [0, 10 s] or whose sequence number is 0, and tracks each sender's numbering so that no sample can
make the later ones look out of order (:mod:`.sequence`).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...errors import AsyncdonkeyError

__all__ = [
    "ATTACHMENT",
    "GROUP",
    "GROUP_VERSION",
    "JPEG",
    "JSON",
    "NDARRAY",
    "OCTET",
    "CodecError",
    "Encoded",
    "decode",
    "decode_group",
    "encode",
    "encode_group",
    "pack_attachment",
    "unpack_attachment",
]

OCTET = "application/octet-stream"
NDARRAY = "application/octet-stream;ndarray"
JPEG = "image/jpeg"
JSON = "application/json"
GROUP = "application/json;group"
GROUP_VERSION = 1
ATTACHMENT = struct.Struct("<dQQ")


class CodecError(AsyncdonkeyError, ValueError):
    """A value cannot be encoded for the network, or a received payload does not match its encoding."""


@dataclass(frozen=True, slots=True)
class Encoded:
    """A payload ready for ``put``: its bytes and the encoding string for Zenoh's encoding field."""

    payload: bytes
    encoding: str


def pack_attachment(age_s: float, seq: int, source: int = 0) -> bytes:
    """The 24-byte attachment: age at send time (s, float64 LE), sequence number and source (uint64 LE each)."""
    return ATTACHMENT.pack(age_s, seq, source)


def unpack_attachment(data: bytes | None) -> tuple[float, int, int] | None:
    """``(age_s, seq, source)`` from an attachment, or ``None`` if it is absent or not ours (a foreign publisher).

    Only the layout is checked here: whether the age and number are plausible is the receiver's judgement
    (:mod:`.sequence`), which counts what it refuses."""
    if data is None or len(data) != ATTACHMENT.size:
        return None
    age, seq, source = ATTACHMENT.unpack(data)
    return age, seq, source


def encode(value: Any, channel: str, *, jpeg_quality: int | None = None) -> Encoded:
    """Encode one Memory value. ``jpeg_quality`` (1-100) sends an image array as JPEG instead of raw bytes.

    An image for JPEG is a ``uint8`` array of shape ``(H, W, 3)`` (RGB) or ``(H, W)`` (grey).
    """
    if isinstance(value, np.ndarray):
        if jpeg_quality is not None:
            return Encoded(_jpeg(value, channel, jpeg_quality), JPEG)
        arr = value
        if arr.dtype.byteorder == ">" or (arr.dtype.byteorder == "=" and np.little_endian is False):
            arr = arr.astype(arr.dtype.newbyteorder("<"))
        if arr.dtype.hasobject or arr.dtype.fields is not None:
            raise CodecError(f"channel {channel!r}: cannot send a numpy array of dtype {arr.dtype} (not plain numbers)")
        arr = np.ascontiguousarray(arr)
        shape = ",".join(str(n) for n in arr.shape)
        return Encoded(arr.tobytes(), f"{NDARRAY};dtype={arr.dtype.str};shape={shape}")
    if isinstance(value, bytes | bytearray | memoryview):
        return Encoded(bytes(value), OCTET)
    if isinstance(value, np.generic):
        value = value.item()
    try:
        text = json.dumps(value, separators=(",", ":"), allow_nan=True, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise CodecError(
            f"channel {channel!r}: cannot send a {type(value).__name__} (numpy arrays, bytes and JSON values are"
            f" supported): {exc}"
        ) from None
    return Encoded(text.encode(), JSON)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray) and obj.size <= 64:
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _jpeg(image: np.ndarray, channel: str, quality: int) -> bytes:
    import cv2

    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise CodecError(
            f"channel {channel!r}: JPEG needs a uint8 image of shape (H, W, 3) or (H, W), got {image.dtype}"
            f" {image.shape}"
        )
    bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV only fails here on invalid input, checked above
        raise CodecError(f"channel {channel!r}: OpenCV could not encode the image as JPEG")
    return buf.tobytes()


def decode(payload: bytes, encoding: str, key: str = "?") -> Any:
    """Decode a payload by its encoding string (as :func:`encode` writes it); ``key`` names it in errors."""
    base, _, schema = encoding.partition(";")
    if base == OCTET and schema.startswith("ndarray"):
        return _ndarray(payload, schema, key)
    if base == OCTET or base == "zenoh/bytes":
        return payload
    if base == JSON or base == "text/json":
        try:
            return json.loads(payload)
        except ValueError as exc:
            raise CodecError(f"key {key!r}: payload is not valid JSON: {exc}") from None
    if base == JPEG:
        import cv2

        img = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CodecError(f"key {key!r}: payload is not a decodable JPEG ({len(payload)} bytes)")
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if base in ("text/plain", "zenoh/string"):
        return payload.decode("utf-8", errors="replace")
    raise CodecError(f"key {key!r}: unsupported encoding {encoding!r} (expected {NDARRAY}, {JPEG}, {JSON} or {OCTET})")


def encode_group(values: dict[str, Any], group: str) -> Encoded:
    """Encode a command group (channel -> value, JSON scalars) as one sample (see the module docstring)."""
    try:
        text = json.dumps(values, separators=(",", ":"), allow_nan=True, default=_json_default)
    except (TypeError, ValueError) as exc:
        raise CodecError(f"group {group!r}: cannot send {list(values)} as JSON: {exc}") from None
    return Encoded(text.encode(), f"{GROUP};v={GROUP_VERSION}")


def decode_group(payload: bytes, encoding: str, channels: tuple[str, ...], key: str = "?") -> tuple[Any, ...]:
    """The values of ``channels``, in that order, from a command group sample; :class:`CodecError` for anything
    but this layout's version with exactly those channels."""
    base, _, schema = encoding.partition(";")
    fields = schema.split(";")
    if base != JSON or fields[0] != "group":
        raise CodecError(f"key {key!r}: expected a command group ({GROUP};v={GROUP_VERSION}), got {encoding!r}")
    params = dict(f.partition("=")[::2] for f in fields[1:])
    if params.get("v") != str(GROUP_VERSION):
        raise CodecError(f"key {key!r}: command group version {params.get('v')!r}, expected {GROUP_VERSION}")
    try:
        doc = json.loads(payload)
    except ValueError as exc:
        raise CodecError(f"key {key!r}: payload is not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or set(doc) != set(channels):
        what = f"keys {sorted(doc)[:8]}" if isinstance(doc, dict) else f"a {type(doc).__name__}"
        raise CodecError(f"key {key!r}: expected an object with exactly {list(channels)}, got {what}")
    return tuple(doc[ch] for ch in channels)


def _ndarray(payload: bytes, schema: str, key: str) -> np.ndarray:
    fields = dict(part.partition("=")[::2] for part in schema.split(";")[1:])
    try:
        dtype = np.dtype(fields["dtype"])
        shape = tuple(int(n) for n in fields["shape"].split(",") if n != "")
    except (KeyError, TypeError, ValueError) as exc:
        raise CodecError(f"key {key!r}: bad ndarray encoding schema {schema!r}: {exc}") from None
    expected = dtype.itemsize * math.prod(shape)
    if len(payload) != expected:
        raise CodecError(f"key {key!r}: ndarray {dtype.str} {shape} needs {expected} bytes, got {len(payload)}")
    # a writable copy: parts downstream may modify a frame in place, as they can a camera's
    return np.frombuffer(payload, dtype=dtype).reshape(shape).copy()
