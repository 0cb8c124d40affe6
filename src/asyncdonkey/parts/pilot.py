"""Pilots: a Donkeycar-style image → (angle, throttle) model on the CPU, from an ONNX or a TFLite file.

Usage, as Donkeycar wires its pilot::

    v.add(load_pilot("models/pilot.onnx"), inputs=["cam/image_array"],      # or a .tflite file
          outputs=["pilot/angle", "pilot/throttle"], run_condition="run_pilot")

:func:`load_pilot` picks the runtime from the file: :class:`OnnxPilot` (onnxruntime, below) for ``.onnx``,
:class:`~asyncdonkey.parts.tflite_pilot.TflitePilot` (LiteRT, the ``tflite`` extra) for ``.tflite``. Both are
:class:`~asyncdonkey.parts.pilot_base.PilotBase`: the same checks, preprocessing, output forms and worker thread.

Notes on :class:`OnnxPilot`:

* **Off the loop thread** (as every pilot part). ``run()`` is ``async``: inference runs in a single-thread
  executor owned by the pilot, so serial readers, pollers and web clients keep being served while it computes,
  and the tick still awaits the result in order. One thread, because one session and one frame at a time is
  all a drive loop needs, and it keeps onnxruntime's own threads the only parallelism (``offload=False`` runs
  inline).
* **Low-latency session.** Intra-op threads = physical cores (hyper-threads only contend for the same
  units), thread spinning off (``session.intra_op.allow_spinning = "0"``: spinning workers would burn the
  cores the rest of the car needs between frames at 20 Hz), sequential execution (a pilot graph is a chain;
  the parallel executor only adds scheduling), all graph optimisations on, CPU provider.
* **Checked at load, not on the first tick** (:mod:`~asyncdonkey.parts.pilot_base`): the input must be a 4-D
  float image; INT8 models from ``asyncdonkey quantize`` (QDQ: float input, quantized inside) run unchanged.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from .pilot_base import (
    IMAGE_SHAPE,
    PilotBase,
    PilotModelError,
    TensorInfo,
    _first_line,
    inference_threads,
    physical_cores,
)

__all__ = [
    "IMAGE_SHAPE",
    "MODEL_SUFFIXES",
    "OnnxPilot",
    "PilotBase",
    "PilotModelError",
    "load_pilot",
    "physical_cores",
]

#: What :func:`load_pilot` runs, by file suffix.
MODEL_SUFFIXES = (".onnx", ".tflite")


def load_pilot(
    model_path: str | os.PathLike[str],
    *,
    threads: int | None = None,
    offload: bool = True,
    name: str | None = None,
    image_shape: tuple[int, int, int] = IMAGE_SHAPE,
    default_throttle: float | None = None,
) -> PilotBase:
    """The pilot part for a model file, the runtime chosen by its suffix: ``.onnx`` → :class:`OnnxPilot`,
    ``.tflite`` → :class:`~asyncdonkey.parts.tflite_pilot.TflitePilot`.

    ``threads`` is the runtime's compute threads (default: physical cores); the other arguments are the
    parts' own. Raises :class:`PilotModelError` naming the file for an unknown suffix (with a hint for
    Donkeycar's Keras files) and whatever the part raises at load; ``ImportError`` with the install hint when
    the ``.tflite`` runtime (the ``tflite`` extra) is missing.
    """
    path = Path(model_path)
    suffix = path.suffix.lower()
    common: dict[str, Any] = {
        "offload": offload,
        "name": name,
        "image_shape": image_shape,
        "default_throttle": default_throttle,
    }
    if suffix == ".onnx":
        return OnnxPilot(path, intra_op_threads=threads, **common)
    if suffix == ".tflite":
        from .tflite_pilot import TflitePilot

        return TflitePilot(path, num_threads=threads, **common)
    hint = ""
    if suffix in (".h5", ".keras", ".savedmodel"):
        hint = " (a Keras model: convert it to .tflite or .onnx first, see docs/pilot.md)"
    raise PilotModelError(
        f"model {path}: cannot tell its runtime from the suffix {suffix or '(none)'!r}; "
        f"expected one of {', '.join(MODEL_SUFFIXES)}{hint}"
    )


def __getattr__(name: str) -> Any:
    if name == "TflitePilot":  # LiteRT is an extra: import it only when asked for
        from .tflite_pilot import TflitePilot

        return TflitePilot
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class OnnxPilot(PilotBase):
    """Run an ONNX pilot on camera frames: ``predict(image) -> (angle, throttle)``, ``async run(image)``.

    Args:
        model_path: the ``.onnx`` file.
        intra_op_threads: onnxruntime's intra-op threads (default: :func:`physical_cores`).
        offload: ``run()`` computes in the pilot's own worker thread (default); ``False`` computes inline.
        name: the name in errors (default ``OnnxPilot(<file name>)``).
        image_shape: the camera frame, ``(rows, columns, 3)``; the model's input must match it.
        default_throttle: the throttle returned with an angle-only model (required for those).

    Attributes:
        inferences: completed ``predict()`` calls.
        last_inference_s: wall-clock seconds the last ``predict()`` took (compute cost, so not the runtime
            clock, which a virtual clock would stop).
        layout: ``"NHWC"`` or ``"NCHW"``, as detected from the model's input.
    """

    thread_name = "onnx-pilot"

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        intra_op_threads: int | None = None,
        offload: bool = True,
        name: str | None = None,
        image_shape: tuple[int, int, int] = IMAGE_SHAPE,
        default_throttle: float | None = None,
    ) -> None:
        super().__init__(model_path, offload=offload, name=name, image_shape=image_shape)
        self.intra_op_threads = inference_threads(intra_op_threads, self.name, "intra_op_threads")
        self._local = threading.local()
        self.session = self._load()
        inputs = [_onnx_info(i) for i in self.session.get_inputs()]
        self.input_name = inputs[0].name if inputs else ""
        self._configure(inputs, [_onnx_info(o) for o in self.session.get_outputs()], default_throttle)

    def _load(self) -> Any:
        import onnxruntime as ort

        self._missing_file()
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.intra_op_threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.log_severity_level = 3  # errors only: onnxruntime's warnings are not the car's business
        try:
            return ort.InferenceSession(str(self.path), sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidProtobuf/... types
            raise PilotModelError(
                f"{self.name}: cannot load model {self.path} ({type(exc).__name__}: {_first_line(exc)})"
            ) from exc

    def _preprocess(self, image: np.ndarray) -> np.ndarray:
        """uint8 frame → float32 ``/ 255`` batch of one in the model's layout, in one pass.

        The result goes into a buffer kept per thread: a fresh 230 kB array per frame is a fresh mmap for
        the allocator, and its page faults cost more than the division. Each thread reuses its own buffer,
        and ``session.run`` has copied it by the time it returns."""
        buf = getattr(self._local, "buf", None)
        if buf is None:
            h, w, c = self.image_shape
            buf = self._local.buf = np.empty((1, h, w, c) if self.layout == "NHWC" else (1, c, h, w), np.float32)
        self.encoder.encode(image, buf[0])
        return buf

    def _infer(self, image: np.ndarray) -> list[np.ndarray]:
        return self.session.run(None, {self.input_name: self._preprocess(image)})

    def __repr__(self) -> str:
        return (
            f"<OnnxPilot {self.path} {self.layout} threads={self.intra_op_threads} "
            f"offload={self.offload} inferences={self.inferences}>"
        )


def _onnx_info(arg: Any) -> TensorInfo:
    """onnxruntime's NodeArg → :class:`TensorInfo` (float tensors only: QDQ models keep float inputs)."""
    shape = tuple(arg.shape) if arg.shape is not None else None
    dtype = np.dtype(np.float32) if arg.type == "tensor(float)" else None
    return TensorInfo(arg.name, shape, arg.type, dtype)  # type: ignore[arg-type]
