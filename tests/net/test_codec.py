"""The wire format: what a sample's payload, encoding and attachment hold, decodable without this package."""

import json
import math
import struct

import numpy as np
import pytest

from asyncdonkey.errors import AsyncdonkeyError
from asyncdonkey.parts.zenoh.codec import (
    JPEG,
    JSON,
    CodecError,
    decode,
    encode,
    pack_attachment,
    unpack_attachment,
)


@pytest.mark.parametrize(
    "arr",
    [
        np.arange(120 * 160 * 3, dtype=np.uint8).reshape(120, 160, 3),
        np.linspace(-1, 1, 7, dtype=np.float32),
        np.arange(6, dtype=">i4").reshape(2, 3),  # big-endian in, little-endian on the wire
        np.zeros((0, 3), dtype=np.float64),
        np.asfortranarray(np.arange(12, dtype=np.int16).reshape(3, 4)),
    ],
)
def test_arrays_round_trip_with_dtype_and_shape(arr):
    enc = encode(arr, "x")
    out = decode(enc.payload, enc.encoding)
    assert out.shape == arr.shape and out.dtype == arr.dtype.newbyteorder("<")
    np.testing.assert_array_equal(out, arr)
    out[...] = 0  # a writable array, like a camera frame


def test_array_format_is_readable_from_the_documented_description_alone():
    arr = np.array([[1.5, -2.0], [3.25, 4.0]], dtype=np.float32)
    enc = encode(arr, "imu/accel")
    base, schema = enc.encoding.split(";", 1)
    assert base == "application/octet-stream"
    fields = dict(f.split("=") for f in schema.split(";")[1:])
    assert schema.startswith("ndarray;") and fields == {"dtype": "<f4", "shape": "2,2"}
    # what a C client does: little-endian float32s in C order
    assert struct.unpack("<4f", enc.payload) == (1.5, -2.0, 3.25, 4.0)


def test_jpeg_images_decode_to_rgb():
    img = np.zeros((120, 160, 3), np.uint8)
    img[:, :80] = (255, 0, 0)  # red left half
    img[:, 80:] = (0, 0, 255)  # blue right half
    enc = encode(img, "cam/image_array", jpeg_quality=90)
    assert enc.encoding == JPEG and enc.payload[:2] == b"\xff\xd8"
    assert len(enc.payload) < img.nbytes / 10
    out = decode(enc.payload, enc.encoding)
    assert out.shape == img.shape and out.dtype == np.uint8
    assert np.abs(out[60, 40].astype(int) - (255, 0, 0)).max() < 8  # still red: channels not swapped
    assert np.abs(out[60, 120].astype(int) - (0, 0, 255)).max() < 8


@pytest.mark.parametrize("value", [0.25, -3, True, None, "local", {"mode": "user", "laps": 2}, [1, 2.5]])
def test_scalars_and_small_dicts_are_json(value):
    enc = encode(value, "user/mode")
    assert enc.encoding == JSON
    assert json.loads(enc.payload) == value
    assert decode(enc.payload, enc.encoding) == value


def test_numpy_scalars_are_sent_as_plain_json_numbers():
    enc = encode(np.float32(0.5), "pilot/angle")
    assert enc.payload == b"0.5"
    assert json.loads(encode({"a": np.int64(3)}, "d").payload) == {"a": 3}


def test_attachment_is_age_sequence_and_source_little_endian():
    att = pack_attachment(0.125, 7, 99)
    assert len(att) == 24 and struct.unpack("<dQQ", att) == (0.125, 7, 99)
    assert unpack_attachment(att) == (0.125, 7, 99)
    assert unpack_attachment(None) is None
    assert unpack_attachment(b"short") is None
    # the layout only: an implausible age or number is the receiver's to refuse and count (test_sequence.py)
    assert unpack_attachment(struct.pack("<dQQ", -1.0, 0, 2**64 - 1)) == (-1.0, 0, 2**64 - 1)
    assert math.isnan(unpack_attachment(struct.pack("<dQQ", float("nan"), 1, 1))[0])


def test_errors_name_the_channel_and_share_the_root():
    with pytest.raises(CodecError, match=r"'odd'.*object") as err:
        encode(object(), "odd")
    assert isinstance(err.value, AsyncdonkeyError)
    with pytest.raises(CodecError, match=r"cam.*uint8"):
        encode(np.zeros((4, 4, 3), np.float32), "cam", jpeg_quality=80)
    with pytest.raises(CodecError, match=r"'k'.*needs 12 bytes, got 8"):
        decode(b"\0" * 8, "application/octet-stream;ndarray;dtype=<f4;shape=3", "k")
    with pytest.raises(CodecError, match="unsupported encoding"):
        decode(b"", "video/h264", "k")
    with pytest.raises(CodecError, match="not valid JSON"):
        decode(b"{", JSON, "k")
    with pytest.raises(CodecError, match="not a decodable JPEG"):
        decode(b"nope", JPEG, "k")
