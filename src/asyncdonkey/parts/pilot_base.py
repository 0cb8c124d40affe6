"""What every pilot part shares, whatever runtime runs its model: frames in, ``(angle, throttle)`` out.

:class:`~asyncdonkey.parts.pilot.OnnxPilot` (onnxruntime) and :class:`~asyncdonkey.parts.tflite_pilot.TflitePilot`
(LiteRT) differ only in how they load a model, describe its tensors and run it once. Everything a car relies on
is here, written once, so the two cannot drift apart:

* **The contract.** ``predict(image) -> (angle, throttle)`` (synchronous: replay, tests) and ``async run(image)``
  (the drive loop: ``(None, None)`` before the first frame; inference in the pilot's own single worker thread,
  so the event loop serves other tasks while the tick awaits the answer), ``shutdown()``, the counters
  ``inferences`` and ``last_inference_s``.
* **Checks at load.** One image input of the configured frame size in NHWC or NCHW, batch 1 or dynamic; the
  outputs in one of the forms below; one warm-up inference on a blank frame settles output sizes the model does
  not declare and pays the first-run cost before the car moves. Errors name the part, the file and the shapes.
* **Preprocessing as Donkeycar's** (uint8 RGB / 255, a batch of one), into the model's input type:
  :class:`FrameEncoder` also feeds quantized (uint8/int8) inputs, ``q = round(x / scale) + zero_point``.
* **Outputs:** one output of two values ``[angle, throttle]``; two outputs of one value (angle first, unless
  they are named ``angle`` and ``throttle``, which then decide); one output of one value (angle only, the
  throttle is ``default_throttle``). Quantized outputs are dequantized, ``(q - zero_point) * scale``; the values
  are clipped to ``[-1, 1]``, and a NaN is an error naming the model.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import AsyncdonkeyError

__all__ = ["IMAGE_SHAPE", "FrameEncoder", "PilotBase", "PilotModelError", "TensorInfo", "physical_cores"]

IMAGE_SHAPE = (120, 160, 3)
Layout = Literal["NHWC", "NCHW"]
Plan = Literal["pair", "two", "angle"]
_UINT8 = np.dtype(np.uint8)


class PilotModelError(AsyncdonkeyError, ValueError):
    """The model file is missing, unreadable or not a pilot this part can run; the message names the file."""


def inference_threads(value: int | None, where: str, arg: str) -> int:
    """The threads a runtime gets: ``value`` (a positive int) or, by default, the physical cores."""
    if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
        raise ValueError(f"{where}: {arg} must be a positive int, got {value!r}")
    return value or physical_cores()


def physical_cores() -> int:
    """Physical CPU cores this process may run on (hyper-threads counted once); at least 1.

    Read from ``/proc/cpuinfo`` (unique ``physical id``/``core id`` pairs) where available, else the CPU count.
    """
    try:
        allowed = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        allowed = os.cpu_count() or 1
    cores: set[tuple[str, str]] = set()
    try:
        with open("/proc/cpuinfo") as f:
            phys = core = ""
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "physical id":
                    phys = value.strip()
                elif key == "core id":
                    core = value.strip()
                elif not line.strip():
                    if core:
                        cores.add((phys, core))
                    phys = core = ""
            if core:
                cores.add((phys, core))
    except OSError:
        pass
    return max(1, min(len(cores) or allowed, allowed))


@dataclass(frozen=True)
class TensorInfo:
    """A model input or output as a runtime describes it, in the terms the checks need.

    ``shape``: ints for static dims, anything else (``None``, a name) for dynamic ones. ``type``: the runtime's
    own spelling, for messages (``tensor(float)``, ``uint8``). ``dtype``: ``float32``, ``uint8`` or ``int8`` when
    the pilot can feed or read it, else ``None``. ``scale``/``zero_point``: the quantization of an integer
    tensor (real value = ``(q - zero_point) * scale``).
    """

    name: str
    shape: tuple[Any, ...]
    type: str
    dtype: np.dtype | None
    scale: float = 0.0
    zero_point: int = 0

    @property
    def quantized(self) -> bool:
        return self.dtype is not None and self.dtype.kind in "iu"

    def describe(self) -> str:
        quant = f" (scale {self.scale:.6g}, zero point {self.zero_point})" if self.quantized else ""
        return f"{self.name!r} {self.type}{quant} {_fmt(self.shape)}"


class FrameEncoder:
    """A uint8 RGB frame into a model input, as Donkeycar prepares it (``x = frame / 255``), in one pass.

    Float inputs get ``frame / 255`` in float32. Quantized inputs get ``round(x / scale) + zero_point`` clipped
    to the type, computed once for the 256 possible pixel values (a table). The usual calibrations make the table
    trivial and the encoding exact and cheap: ``scale = 1/255`` with zero point 0 (uint8) is the frame itself,
    with zero point -128 (int8) is the frame with its top bit flipped; other calibrations look the table up.
    """

    def __init__(self, layout: Layout, dtype: Any = np.float32, scale: float = 0.0, zero_point: int = 0) -> None:
        self.layout = layout
        self.dtype = np.dtype(dtype)
        self.scale = float(scale)
        self.zero_point = int(zero_point)
        self.table: np.ndarray | None = None
        if self.dtype == np.float32:
            self.mode = "divide"
            return
        if self.dtype not in (np.dtype(np.uint8), np.dtype(np.int8)):
            raise ValueError(f"FrameEncoder: cannot feed {self.dtype}; expected float32, uint8 or int8")
        if not (self.scale > 0 and math.isfinite(self.scale)):
            raise ValueError(f"FrameEncoder: a quantized input needs a positive scale, got {scale!r}")
        info = np.iinfo(self.dtype)
        real = np.arange(256, dtype=np.float64) / 255.0
        table = np.clip(np.round(real / self.scale) + self.zero_point, info.min, info.max).astype(self.dtype)
        values = table.astype(np.int16)
        if np.array_equal(values, np.arange(256)):
            self.mode = "copy"
        elif np.array_equal(values, np.arange(256) - 128):
            self.mode = "flip"
        else:
            self.mode = "table"
        self.table = table

    def encode(self, image: np.ndarray, out: np.ndarray) -> None:
        """Write ``image`` (rows, columns, 3) uint8 into ``out``: one batch item, in the model's layout and type."""
        mode = self.mode
        if self.layout == "NHWC":
            if mode == "divide":
                # widen, then divide in place: twice as fast as numpy's mixed-type divide, and the same bits
                np.copyto(out, image, casting="unsafe")
                np.divide(out, np.float32(255.0), out=out)
            elif mode == "flip":  # v - 128 as int8 is v with its top bit flipped, read as int8
                np.bitwise_xor(image, np.uint8(0x80), out=out.view(np.uint8))
            elif mode == "copy":
                np.copyto(out, image)
            else:
                self._look_up(image, out)
            return
        src = image.transpose(2, 0, 1)
        if mode == "divide":
            np.divide(src, np.float32(255.0), out=out, dtype=np.float32)
        elif mode == "flip":
            np.bitwise_xor(src, np.uint8(0x80), out=out.view(np.uint8))
        elif mode == "copy":
            np.copyto(out, src)
        else:
            np.copyto(out, self._look_up(image, None).transpose(2, 0, 1))

    def _look_up(self, image: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        """The table applied to every pixel, with OpenCV's ``LUT`` (a tenth of the time of numpy's indexing)."""
        import cv2

        table = self.table.view(np.uint8)  # type: ignore[union-attr]  # int8 tables go through as their bytes
        if out is None:
            return cv2.LUT(image, table).view(self.dtype)
        return cv2.LUT(np.ascontiguousarray(image), table, dst=out.view(np.uint8))


class PilotBase:
    """The runtime-independent part of a pilot (see the module docstring). Subclasses load the model, then call
    :meth:`_configure` with its input and outputs, and implement :meth:`_infer` (one frame, raw outputs)."""

    #: prefix of the worker thread's name
    thread_name = "pilot"
    #: what the input may be, for the error message
    accepted_inputs = "a 4-D float tensor (batch, image)"

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        offload: bool,
        name: str | None,
        image_shape: tuple[int, int, int],
    ) -> None:
        self.path = Path(model_path)
        self.name = name or f"{type(self).__name__}({self.path.name})"
        self.image_shape = tuple(int(d) for d in image_shape)
        if len(self.image_shape) != 3 or self.image_shape[2] != 3:
            raise ValueError(f"{self.name}: image_shape must be (rows, columns, 3), got {image_shape!r}")
        self.offload = bool(offload)
        self.inferences = 0
        self.last_inference_s = math.nan
        self.layout: Layout = "NHWC"
        self.default_throttle: float | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._closed = False

    # ------------------------------------------------------------------------------------ to implement
    def _infer(self, image: np.ndarray) -> Sequence[np.ndarray]:
        """Run the model on one checked frame; the raw outputs in the model's order."""
        raise NotImplementedError

    # ---------------------------------------------------------------------------------------- loading
    def _missing_file(self) -> None:
        if not self.path.is_file():
            raise PilotModelError(f"{self.name}: model file {self.path} does not exist")

    def _configure(
        self, inputs: Sequence[TensorInfo], outputs: Sequence[TensorInfo], default_throttle: float | None
    ) -> None:
        """Check the model's tensors, choose the encoder and the output plan, warm up (see the module doc)."""
        self.input_info = self._check_input(inputs)
        self.encoder = FrameEncoder(
            self.layout, self.input_info.dtype, self.input_info.scale, self.input_info.zero_point
        )
        self.output_info = tuple(outputs)
        self._output_plan: Plan = self._check_outputs(self.output_info)
        self._dequant = [(o.scale, o.zero_point) if o.quantized else None for o in self.output_info]
        self._swap = False
        self._warm_up()
        if self._output_plan == "angle" and default_throttle is None:
            raise PilotModelError(
                f"{self.name}: model {self.path} outputs the angle only; pass default_throttle= for the throttle"
            )
        self.default_throttle = None if default_throttle is None else float(default_throttle)

    def _check_input(self, inputs: Sequence[TensorInfo]) -> TensorInfo:
        if len(inputs) != 1:
            raise PilotModelError(
                f"{self.name}: model {self.path} has {len(inputs)} inputs {[i.name for i in inputs]}; "
                "a pilot takes one image"
            )
        inp = inputs[0]
        shape = list(inp.shape)
        if inp.dtype is None or len(shape) != 4:
            raise PilotModelError(
                f"{self.name}: model {self.path} input {inp.name!r} is {inp.type} {_fmt(shape)}; "
                f"expected {self.accepted_inputs}"
            )
        batch = shape[0]
        if isinstance(batch, int) and batch != 1:
            raise PilotModelError(
                f"{self.name}: model {self.path} input {inp.name!r} has batch {batch}; expected 1 or dynamic"
            )
        h, w, c = self.image_shape
        dims = shape[1:]
        if _matches(dims, [h, w, c]):
            self.layout = "NHWC"
        elif _matches(dims, [c, h, w]):
            self.layout = "NCHW"
        else:
            raise PilotModelError(
                f"{self.name}: model {self.path} wants input {inp.name!r} {_fmt(shape)}, but frames are "
                f"{h}x{w}x{c} (expected [1, {h}, {w}, {c}] NHWC or [1, {c}, {h}, {w}] NCHW; image_shape="
                f"{self.image_shape})"
            )
        return inp

    def _check_outputs(self, outs: Sequence[TensorInfo]) -> Plan:
        sizes = [_static_size(o.shape) for o in outs]
        desc = ", ".join(o.describe() for o in outs)
        bad = PilotModelError(
            f"{self.name}: model {self.path} outputs {desc}; expected one output of 2 values (angle, throttle), "
            "two outputs of 1 value (angle, throttle) or one output of 1 value (angle)"
        )
        if any(o.dtype is None for o in outs):
            raise bad
        if len(outs) == 1 and sizes[0] in (2, None):
            return "pair" if sizes[0] == 2 else "angle"  # unknown size: settled by the warm-up run
        if len(outs) == 1 and sizes[0] == 1:
            return "angle"
        if len(outs) == 2 and all(s in (1, None) for s in sizes):
            return "two"
        raise bad

    def _warm_up(self) -> None:
        """One inference on a blank frame: checks the real output sizes and pays the first-run cost now."""
        outs = self._infer(np.zeros(self.image_shape, np.uint8))
        sizes = [int(np.size(o)) for o in outs]
        plan = self._output_plan
        if plan == "angle" and sizes == [2]:
            self._output_plan = plan = "pair"
        want = {"pair": [2], "two": [1, 1], "angle": [1]}[plan]
        if sizes != want:
            raise PilotModelError(
                f"{self.name}: model {self.path} produced outputs of {sizes} values on a test frame; "
                "expected one output of 2 values, two of 1 value or one of 1 value"
            )
        names = [o.name.lower() for o in self.output_info]
        self._swap = plan == "two" and names == ["throttle", "angle"]

    # ---------------------------------------------------------------------------------------- inference
    def predict(self, image: np.ndarray) -> tuple[float, float]:
        """One frame (``image_shape`` uint8 RGB) → ``(angle, throttle)``, each clipped to ``[-1, 1]``.

        Synchronous: for replay, tests and the executor. Raises ``ValueError`` naming the part for a frame of
        the wrong shape or type, or when the model produces NaN.
        """
        if not isinstance(image, np.ndarray) or image.shape != self.image_shape or image.dtype != _UINT8:
            got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else f"a {type(image).__name__}"
            raise ValueError(f"{self.name}: cam/image_array frame is {got}; expected {self.image_shape} uint8 RGB")
        t0 = time.perf_counter()
        outs = self._infer(image)
        dq = self._dequant
        plan = self._output_plan
        if plan == "pair":
            out = outs[0]
            angle, throttle = float(out.item(0)), float(out.item(1))
            if dq[0] is not None:
                scale, zp = dq[0]
                angle, throttle = (angle - zp) * scale, (throttle - zp) * scale
        elif plan == "two":
            angle, throttle = _value(outs[0], dq[0]), _value(outs[1], dq[1])
            if self._swap:
                angle, throttle = throttle, angle
        else:
            angle, throttle = _value(outs[0], dq[0]), self.default_throttle  # type: ignore[assignment]
        if math.isnan(angle) or math.isnan(throttle):
            raise ValueError(f"{self.name}: model {self.path} produced NaN (angle {angle}, throttle {throttle})")
        self.last_inference_s = time.perf_counter() - t0
        self.inferences += 1
        return _clip(angle), _clip(throttle)

    def batch_commands(self, raw: Sequence[np.ndarray], n: int) -> tuple[np.ndarray, np.ndarray]:
        """The raw outputs of one model call on ``n`` frames → ``(angles, throttles)``, float64 arrays of ``n``.

        The outputs are read exactly as :meth:`predict` reads one frame's (the output plan found at load time,
        dequantization, the throttle/angle order, the default throttle of an angle-only model), so a server that
        infers many cars' frames in one call answers each car as this pilot would alone. Values are not clipped
        and NaN is kept: the caller decides what a NaN frame gets.
        """
        cols = [np.asarray(o, dtype=np.float64).reshape(n, -1) for o in raw]
        for k, d in enumerate(self._dequant):
            if d is not None:
                cols[k] = (cols[k] - d[1]) * d[0]
        plan = self._output_plan
        if plan == "pair":
            return cols[0][:, 0], cols[0][:, 1]
        if plan == "two":
            angles, throttles = cols[0][:, 0], cols[1][:, 0]
            return (throttles, angles) if self._swap else (angles, throttles)
        return cols[0][:, 0], np.full(n, self.default_throttle, np.float64)

    async def run(self, image: np.ndarray | None) -> tuple[float | None, float | None]:
        """The drive-loop entry: ``(angle, throttle)`` for the frame, ``(None, None)`` before the first frame.

        With ``offload`` the inference runs in the pilot's worker thread while the event loop serves other
        tasks; the tick still waits for the result.
        """
        if image is None:
            return None, None
        if not self.offload:
            return self.predict(image)
        if self._closed:
            raise RuntimeError(f"{self.name}: run() after shutdown()")
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=self.thread_name)
        return await asyncio.get_running_loop().run_in_executor(self._executor, self.predict, image)

    def shutdown(self) -> None:
        """Release the worker thread (waits for an inference in progress)."""
        self._closed = True
        ex, self._executor = self._executor, None
        if ex is not None:
            ex.shutdown(wait=True)


def _value(out: np.ndarray, dq: tuple[float, int] | None) -> float:
    v = float(out.item(0))
    return v if dq is None else (v - dq[1]) * dq[0]


def _matches(dims: list[Any], want: list[int]) -> bool:
    """Static dims must equal ``want``; symbolic (named or unknown) dims accept any size."""
    return all(not isinstance(d, int) or d == w for d, w in zip(dims, want, strict=True))


def _static_size(shape: Sequence[Any] | None) -> int | None:
    """Values per batch item when every non-batch dim is static, else ``None`` (the batch dim is ignored
    when the output is at least 2-D)."""
    if shape is None:
        return None
    shape = list(shape)
    dims = shape[1:] if len(shape) >= 2 else shape
    if not all(isinstance(d, int) for d in dims):
        return None
    return int(np.prod(dims)) if dims else 1


def _fmt(shape: Any) -> str:
    if shape is None:
        return "[?]"
    return "[" + ", ".join(str(d) if d is not None else "?" for d in shape) + "]"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:300] if text else "no message"


def _clip(v: float) -> float:
    return -1.0 if v < -1.0 else (1.0 if v > 1.0 else v)
