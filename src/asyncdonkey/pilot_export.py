"""Build small ONNX pilots with the ``onnx`` package: the simulator's linear pilot and a Donkeycar-shaped CNN.

Two kinds of model come out of here:

* :func:`export_linear_pilot` writes ``features(image) @ W + b`` as one graph. :func:`linear_features` is the
  numpy twin of the feature part of that graph, computed from a uint8 frame: training
  (:mod:`asyncdonkey.parts.sim.training`) fits ``W, b`` on exactly what the exported model computes at run
  time (they agree to about 1e-5).
* :func:`export_donkey_linear_shaped` writes a model with the layers of Donkeycar's ``KerasLinear`` and
  deterministic random weights: realistic compute for benchmarks and for trying the pilot part out before a
  real model is trained.

Why these features (a linear model on raw pixels is linear in the pixels, whatever linear transform comes
first, so the features need one non-linearity to be worth more than a reshaped image):

1. Keep the rows below the horizon (:data:`TOP_ROW` = 40; the sky says nothing about steering).
2. Mix the three colour channels per pixel into :data:`N_CHANNELS` maps, then ``Relu``: grey level (the road's
   shape against the grass), a "white" map that is positive only on the near-white edge lines, a "yellow"
   map positive only on the centre line, and a "green" map for the grass. The thresholds make the lane
   markings stand out from asphalt and grass, which a linear mix of channels alone cannot do.
3. Average over :data:`POOL` x :data:`POOL` blocks: 10 x 20 cells per map, 800 features in all.

Every step is an op every ONNX runtime has (Slice, MatMul, Add, Relu, Transpose, AveragePool, Reshape), and
the model is written with IR version :data:`IR_VERSION` and opset :data:`OPSET`, which onnxruntime releases
from 1.13 on read (``onnx`` 1.23 would otherwise write IR 14, newer than onnxruntime 1.31 accepts).

Output bytes are deterministic for the same arguments: no timestamps, fixed producer fields, initialisers
in a fixed order.

``onnx`` is only needed to *write* models (the ``quantize`` extra installs it); it is imported inside the functions
that need it, so importing this module (for :func:`linear_features`, say) works without it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .extras import require

__all__ = [
    "DONKEY_CONVS",
    "DONKEY_DENSE",
    "FEATURE_SIZE",
    "IMAGE_SHAPE",
    "INPUT_NAME",
    "IR_VERSION",
    "OPSET",
    "SMALL_CONVS",
    "SMALL_DENSE",
    "DonkeyLinearWeights",
    "donkey_linear_weights",
    "export_donkey_linear_shaped",
    "export_linear_pilot",
    "linear_features",
]

Layout = Literal["NHWC", "NCHW"]

IMAGE_SHAPE = (120, 160, 3)
"""Donkeycar's camera frame: rows, columns, RGB."""
INPUT_NAME = "img_in"
"""Donkeycar's Keras models name their image input ``img_in``; ours do too."""
IR_VERSION = 8
OPSET = 17
PRODUCER = "asyncdonkey.pilot_export"
PRODUCER_VERSION = "1"

TOP_ROW = 40
"""First image row used: the horizon of the simulator's camera is near row 35."""
POOL = 8
#: Per-pixel channel mix (RGB in [0, 1] -> maps) and the bias before the Relu, one column per map.
#: grey: luminance; white: the darkest channel above 0.7 (edge lines, not asphalt); yellow: red+green
#: over blue (the centre line); green: green over red and blue (grass).
CHANNEL_MIX = np.array(
    [
        # grey   white   yellow  green
        [0.299, 0.0, 0.5, -0.5],  # R
        [0.587, 0.0, 0.5, 1.0],  # G
        [0.114, 1.0, -1.0, -0.5],  # B
    ],
    dtype=np.float32,
)
CHANNEL_BIAS = np.array([0.0, -0.55, -0.25, -0.05], dtype=np.float32)
N_CHANNELS = CHANNEL_MIX.shape[1]
FEATURE_SIZE = N_CHANNELS * ((IMAGE_SHAPE[0] - TOP_ROW) // POOL) * (IMAGE_SHAPE[1] // POOL)


def linear_features(image: np.ndarray) -> np.ndarray:
    """Features of one frame, ``(120, 160, 3)`` uint8 RGB → ``(FEATURE_SIZE,)`` float32.

    Exactly what the graph written by :func:`export_linear_pilot` computes from the same frame scaled to
    ``[0, 1]`` (channel-major: all cells of map 0, then map 1, ...).
    """
    if not (isinstance(image, np.ndarray) and image.shape == IMAGE_SHAPE and image.dtype == np.uint8):
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        raise ValueError(f"linear_features: expected a {IMAGE_SHAPE} uint8 RGB frame, got shape {shape} {dtype}")
    x = image[TOP_ROW:].astype(np.float32) / np.float32(255.0)
    maps = np.maximum(x @ CHANNEL_MIX + CHANNEL_BIAS, np.float32(0.0))  # (80, 160, C)
    h, w, c = maps.shape
    pooled = maps.reshape(h // POOL, POOL, w // POOL, POOL, c).mean(axis=(1, 3), dtype=np.float32)
    return np.ascontiguousarray(pooled.transpose(2, 0, 1)).ravel()


def export_linear_pilot(path: str | os.PathLike[str], W: np.ndarray, b: np.ndarray, *, layout: Layout = "NHWC") -> Path:
    """Write ``[angle, throttle] = linear_features(img) @ W + b`` as an ONNX model; returns the path.

    Input ``img_in``: float32 ``[1, 120, 160, 3]`` (``layout="NHWC"``, Donkeycar's) or ``[1, 3, 120, 160]``
    (``"NCHW"``), the frame scaled to ``[0, 1]``. Outputs ``angle`` and ``throttle``, each ``[1, 1]`` (the
    two-output form of Donkeycar's linear model, whose Keras outputs are ``n_outputs0`` and ``n_outputs1``;
    named here for what they are). ``W`` is ``(FEATURE_SIZE, 2)``, ``b`` is ``(2,)``.
    """
    onnx, helper, numpy_helper = _onnx()
    W = np.asarray(W, dtype=np.float32)
    b = np.asarray(b, dtype=np.float32).reshape(-1)
    if W.shape != (FEATURE_SIZE, 2) or b.shape != (2,):
        raise ValueError(f"export_linear_pilot: W must be ({FEATURE_SIZE}, 2) and b (2,), got {W.shape} and {b.shape}")
    nodes: list[Any] = []
    inits = [
        numpy_helper.from_array(np.array([TOP_ROW], np.int64), "crop_start"),
        numpy_helper.from_array(np.array([IMAGE_SHAPE[0]], np.int64), "crop_end"),
        numpy_helper.from_array(np.array([1], np.int64), "crop_axis"),
        numpy_helper.from_array(CHANNEL_MIX, "channel_mix"),
        numpy_helper.from_array(CHANNEL_BIAS, "channel_bias"),
        numpy_helper.from_array(np.array([1, FEATURE_SIZE], np.int64), "flat_shape"),
        numpy_helper.from_array(W, "W"),
        numpy_helper.from_array(b, "b"),
        numpy_helper.from_array(np.array([0], np.int64), "col0"),
        numpy_helper.from_array(np.array([1], np.int64), "col1"),
        numpy_helper.from_array(np.array([2], np.int64), "col2"),
    ]
    src = _nhwc_input(nodes, helper, layout)
    nodes += [
        helper.make_node("Slice", [src, "crop_start", "crop_end", "crop_axis"], ["crop"]),  # rows below horizon
        helper.make_node("MatMul", ["crop", "channel_mix"], ["mixed"]),  # [1, 80, 160, C]
        helper.make_node("Add", ["mixed", "channel_bias"], ["biased"]),
        helper.make_node("Relu", ["biased"], ["maps"]),
        helper.make_node("Transpose", ["maps"], ["maps_nchw"], perm=[0, 3, 1, 2]),
        helper.make_node("AveragePool", ["maps_nchw"], ["pooled"], kernel_shape=[POOL, POOL], strides=[POOL, POOL]),
        helper.make_node("Reshape", ["pooled", "flat_shape"], ["features"]),
        helper.make_node("MatMul", ["features", "W"], ["linear"]),
        helper.make_node("Add", ["linear", "b"], ["both"]),  # [1, 2]
        helper.make_node("Slice", ["both", "col0", "col1", "col1"], ["angle"]),
        helper.make_node("Slice", ["both", "col1", "col2", "col1"], ["throttle"]),
    ]
    outputs = [_float_tensor(helper, onnx, "angle", [1, 1]), _float_tensor(helper, onnx, "throttle", [1, 1])]
    return _save(path, nodes, inits, outputs, layout, "asyncdonkey_linear_pilot")


#: Donkeycar's ``KerasLinear`` convolutions: (filters, kernel, stride), valid padding, Relu.
DONKEY_CONVS: tuple[tuple[int, int, int], ...] = ((24, 5, 2), (32, 5, 2), (64, 5, 2), (64, 3, 1), (64, 3, 1))
#: Donkeycar's ``KerasLinear`` dense layers (Relu) before the two heads.
DONKEY_DENSE: tuple[int, ...] = (100, 50)
#: A Donkeycar-shaped model small enough to commit (tens of kB): the test models built with TensorFlow.
SMALL_CONVS: tuple[tuple[int, int, int], ...] = ((8, 5, 2), (12, 5, 2), (16, 5, 2), (16, 3, 2))
SMALL_DENSE: tuple[int, ...] = (16,)


@dataclass(frozen=True)
class DonkeyLinearWeights:
    """Seeded weights of a Donkeycar-shaped linear model, in one neutral form for every exporter.

    ``convs``: ``(weight (filters, channels, k, k), bias (filters,), stride)`` per convolution (ONNX's OIHW;
    Keras wants ``weight.transpose(2, 3, 1, 0)``); ``dense``: ``(weight (in, out), bias (out,))`` per Relu layer
    on the features flattened channels-last (Keras's order); ``heads``: the angle then the throttle head, each
    ``(weight (in, 1), bias (1,))``.
    """

    convs: tuple[tuple[np.ndarray, np.ndarray, int], ...]
    dense: tuple[tuple[np.ndarray, np.ndarray], ...]
    heads: tuple[tuple[np.ndarray, np.ndarray], ...]
    feature_shape: tuple[int, int, int]
    """rows, columns, channels after the last convolution."""


def donkey_linear_weights(
    seed: int = 0,
    convs: tuple[tuple[int, int, int], ...] = DONKEY_CONVS,
    dense: tuple[int, ...] = DONKEY_DENSE,
    width: float = 1.0,
) -> DonkeyLinearWeights:
    """He-initialised weights from ``seed`` for the given layers (zero biases but the heads' small ones).

    The same arrays for the same arguments on every machine (numpy's ``default_rng``), which is what lets a
    model built elsewhere (with TensorFlow, say) be checked against an ONNX model of the same weights."""
    rng = np.random.default_rng(seed)
    channels, h, w = IMAGE_SHAPE[2], IMAGE_SHAPE[0], IMAGE_SHAPE[1]
    conv_w = []
    for filters, k, stride in convs:
        fan_in = channels * k * k
        weight = rng.normal(0.0, np.sqrt(2.0 / fan_in), (filters, channels, k, k)).astype(np.float32)
        conv_w.append((weight, np.zeros(filters, np.float32), stride))
        channels = filters
        h, w = (h - k) // stride + 1, (w - k) // stride + 1
        if h < 1 or w < 1:
            raise ValueError(f"donkey_linear_weights: convolutions {convs} shrink a {IMAGE_SHAPE} frame to nothing")
    width = channels * h * w
    dense_w = []
    for units in dense:
        weight = rng.normal(0.0, np.sqrt(2.0 / width), (width, units)).astype(np.float32)
        dense_w.append((weight, np.zeros(units, np.float32)))
        width = units
    heads = []
    for _ in range(2):
        # small heads keep the untrained outputs inside [-1, 1] most of the time
        head = rng.normal(0.0, 0.1 / np.sqrt(width), (width, 1)).astype(np.float32)
        heads.append((head, np.zeros(1, np.float32)))
    return DonkeyLinearWeights(tuple(conv_w), tuple(dense_w), tuple(heads), (h, w, channels))


def export_donkey_linear_shaped(
    path: str | os.PathLike[str],
    seed: int = 0,
    layout: Layout = "NHWC",
    *,
    convs: tuple[tuple[int, int, int], ...] = DONKEY_CONVS,
    dense: tuple[int, ...] = DONKEY_DENSE,
    width: float = 1.0,
) -> Path:
    """Write a model with the layers of Donkeycar's ``KerasLinear`` and random (seeded) weights.

    ``width`` scales every layer's filter count (compute grows about as its square): a way to make a model
    that costs what a Raspberry Pi's inference costs (tens of ms) on a faster machine, for timing studies.

    Conv 24 5x5/2, 32 5x5/2, 64 5x5/2, 64 3x3/1, 64 3x3/1 (valid padding, Relu), flatten, Dense 100 and 50
    (Relu), then two Dense(1) heads ``n_outputs0`` (angle) and ``n_outputs1`` (throttle), each ``[1, 1]``, as
    tf2onnx names Donkeycar's outputs. Dropout layers do nothing at inference and are left out. The weights
    are :func:`donkey_linear_weights` of ``seed``, so the compute is realistic and the bytes are the same every
    time; it does not drive. ``convs`` and ``dense`` change the layers (:data:`SMALL_CONVS`,
    :data:`SMALL_DENSE`: the small model of the committed TFLite test files); ``width`` then scales the
    convolutions' filter counts.
    """
    onnx, helper, numpy_helper = _onnx()
    if not (isinstance(width, int | float) and width > 0):
        raise ValueError(f"export_donkey_linear_shaped: width must be a positive number, got {width!r}")
    if width != 1.0:
        convs = tuple((max(1, round(filters * width)), k, stride) for filters, k, stride in convs)
    weights = donkey_linear_weights(seed, convs, dense)
    nodes: list[Any] = []
    inits: list[Any] = []
    src = _nhwc_input(nodes, helper, layout)
    nodes.append(helper.make_node("Transpose", [src], ["x_nchw"], perm=[0, 3, 1, 2]))
    x = "x_nchw"
    for i, (weight, bias, stride) in enumerate(weights.convs):
        k = weight.shape[2]
        inits += [numpy_helper.from_array(weight, f"conv{i}_w"), numpy_helper.from_array(bias, f"conv{i}_b")]
        nodes += [
            helper.make_node(
                "Conv", [x, f"conv{i}_w", f"conv{i}_b"], [f"conv{i}"], kernel_shape=[k, k], strides=[stride, stride]
            ),
            helper.make_node("Relu", [f"conv{i}"], [f"relu{i}"]),
        ]
        x = f"relu{i}"
    # Keras flattens channels-last: transpose back before the reshape so the Dense weights mean the same
    nodes.append(helper.make_node("Transpose", [x], ["features_nhwc"], perm=[0, 2, 3, 1]))
    flat = int(np.prod(weights.feature_shape))
    inits.append(numpy_helper.from_array(np.array([1, flat], np.int64), "flat_shape"))
    nodes.append(helper.make_node("Reshape", ["features_nhwc", "flat_shape"], ["flat"]))
    x = "flat"
    for i, (weight, bias) in enumerate(weights.dense):
        inits += [numpy_helper.from_array(weight, f"fc{i}_w"), numpy_helper.from_array(bias, f"fc{i}_b")]
        nodes.append(helper.make_node("Gemm", [x, f"fc{i}_w", f"fc{i}_b"], [f"fc{i}"]))
        nodes.append(helper.make_node("Relu", [f"fc{i}"], [f"fc{i}_relu"]))
        x = f"fc{i}_relu"
    outputs = []
    for i, (head, bias) in enumerate(weights.heads):
        inits += [numpy_helper.from_array(head, f"out{i}_w"), numpy_helper.from_array(bias, f"out{i}_b")]
        nodes.append(helper.make_node("Gemm", [x, f"out{i}_w", f"out{i}_b"], [f"n_outputs{i}"]))
        outputs.append(_float_tensor(helper, onnx, f"n_outputs{i}", [1, 1]))
    return _save(path, nodes, inits, outputs, layout, "donkey_linear_shaped")


# ---------------------------------------------------------------------------------------------- helpers
def _onnx() -> tuple[Any, Any, Any]:
    onnx = require("onnx", "quantize", "writing ONNX pilots (asyncdonkey.pilot_export)")
    from onnx import helper, numpy_helper

    return onnx, helper, numpy_helper


def _check_layout(layout: str) -> None:
    if layout not in ("NHWC", "NCHW"):
        raise ValueError(f"layout must be 'NHWC' or 'NCHW', got {layout!r}")


def _nhwc_input(nodes: list[Any], helper: Any, layout: str) -> str:
    """The name of the image as NHWC inside the graph: the input itself, or its transpose for NCHW."""
    _check_layout(layout)
    if layout == "NHWC":
        return INPUT_NAME
    nodes.append(helper.make_node("Transpose", [INPUT_NAME], ["img_nhwc"], perm=[0, 2, 3, 1]))
    return "img_nhwc"


def _float_tensor(helper: Any, onnx: Any, name: str, shape: list[int]) -> Any:
    return helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, shape)


def _save(
    path: str | os.PathLike[str], nodes: list[Any], inits: list[Any], outputs: list[Any], layout: str, graph: str
) -> Path:
    onnx, helper, _ = _onnx()
    h, w, c = IMAGE_SHAPE
    shape = [1, h, w, c] if layout == "NHWC" else [1, c, h, w]
    g = helper.make_graph(nodes, graph, [_float_tensor(helper, onnx, INPUT_NAME, shape)], outputs, initializer=inits)
    model = helper.make_model(
        g,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name=PRODUCER,
        producer_version=PRODUCER_VERSION,
    )
    model.ir_version = IR_VERSION
    model.doc_string = f"{graph}, input {INPUT_NAME} {layout} float32 in [0, 1]"
    onnx.checker.check_model(model)
    out = Path(path)
    data = model.SerializeToString(deterministic=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, out)
    return out
