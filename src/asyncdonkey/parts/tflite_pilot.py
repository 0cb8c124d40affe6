"""TFLite autopilot: a Donkeycar ``.tflite`` pilot (float32 or full-integer INT8) run with LiteRT on the CPU.

::

    v.add(TflitePilot("models/mypilot.tflite"), inputs=["cam/image_array"],
          outputs=["pilot/angle", "pilot/throttle"], run_condition="run_pilot")

The runtime is LiteRT (PyPI ``ai-edge-litert``, the ``tflite`` extra), the maintained TFLite interpreter that
Donkeycar 5.4 itself uses; where only its predecessor ``tflite-runtime`` is installed (older Raspberry Pi
images), that one is used: the API is the same.

Everything but loading and one inference is :class:`~asyncdonkey.parts.pilot_base.PilotBase`, shared with
:class:`~asyncdonkey.parts.pilot.OnnxPilot`. What is TFLite's own:

* **Donkeycar's files load as they are.** A converted ``KerasLinear`` has one input ``img_in`` ``[-1, 120, 160,
  3]`` and outputs ``n_outputs0`` (angle) and ``n_outputs1`` (throttle), but the interpreter may list its output
  tensors in another order: when the model has one signature (Donkeycar's ``serving_default``) the outputs are
  taken in the signature's order, which is the one Donkeycar's ``TfLite`` interpreter uses, and by name when
  they are called ``angle`` and ``throttle``.
* **Quantized models** (full-integer INT8, uint8 or int8 input and outputs): the frame is quantized with the
  input's scale and zero point (exactly and cheaply for the usual ``1/255`` calibrations), the outputs are
  dequantized with theirs. ``input_info`` / ``output_info`` show them.
* **Zero-copy input.** The frame is encoded straight into the interpreter's input buffer; a lock keeps one
  inference at a time (the interpreter is not thread-safe; ``run()`` uses one worker thread, and ``predict()``
  from another thread waits its turn).
* **Threads:** ``num_threads`` (default: physical cores) for LiteRT's CPU kernels (XNNPACK).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..extras import require
from .pilot_base import (
    IMAGE_SHAPE,
    PilotBase,
    PilotModelError,
    TensorInfo,
    _first_line,
    inference_threads,
)

__all__ = ["INTERPRETER_MODULES", "TflitePilot", "tflite_interpreter"]

#: Where the TFLite interpreter is looked for, in order: LiteRT, then the older tflite-runtime.
INTERPRETER_MODULES = ("ai_edge_litert.interpreter", "tflite_runtime.interpreter")
_TYPES = {np.dtype(np.float32), np.dtype(np.uint8), np.dtype(np.int8)}


def tflite_interpreter() -> Any:
    """The ``Interpreter`` class of the first of :data:`INTERPRETER_MODULES` that imports.

    Raises :class:`~asyncdonkey.extras.MissingExtra` (an ``ImportError``) naming the ``tflite`` extra."""
    return require(INTERPRETER_MODULES, "tflite", "running .tflite pilots").Interpreter


class TflitePilot(PilotBase):
    """Run a TFLite pilot on camera frames: ``predict(image) -> (angle, throttle)``, ``async run(image)``.

    Args:
        model_path: the ``.tflite`` file.
        num_threads: LiteRT's CPU threads (default: :func:`physical_cores`).
        offload: ``run()`` computes in the pilot's own worker thread (default); ``False`` computes inline.
        name: the name in errors (default ``TflitePilot(<file name>)``).
        image_shape: the camera frame, ``(rows, columns, 3)``; the model's input must match it.
        default_throttle: the throttle returned with an angle-only model (required for those).

    Attributes:
        inferences, last_inference_s, layout: as :class:`~asyncdonkey.parts.pilot.OnnxPilot`.
        input_info, output_info: the model's input and outputs (name, shape, type, scale, zero point), outputs
            in the order the pilot reads them.
        interpreter: the LiteRT interpreter.
    """

    thread_name = "tflite-pilot"
    accepted_inputs = "a 4-D float32, uint8 or int8 tensor (batch, image)"

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        num_threads: int | None = None,
        offload: bool = True,
        name: str | None = None,
        image_shape: tuple[int, int, int] = IMAGE_SHAPE,
        default_throttle: float | None = None,
    ) -> None:
        super().__init__(model_path, offload=offload, name=name, image_shape=image_shape)
        self.num_threads = inference_threads(num_threads, self.name, "num_threads")
        self._lock = threading.Lock()
        self._batch = 1  # the input's batch size now (infer_batch resizes it)
        self.interpreter = self._load()
        inputs = self.interpreter.get_input_details()
        outputs = self._ordered_outputs()
        self._input_index = int(inputs[0]["index"]) if inputs else -1
        self._output_indices = [int(d["index"]) for d in outputs]
        self._configure(
            [_info(d) for d in inputs], [_info(d, name) for d, name in self._named(outputs)], default_throttle
        )

    # ------------------------------------------------------------------------------------------ loading
    def _load(self) -> Any:
        interpreter_class = tflite_interpreter()
        self._missing_file()
        try:
            interp = interpreter_class(model_path=str(self.path), num_threads=self.num_threads)
        except Exception as exc:  # LiteRT raises ValueError/RuntimeError with multi-line text
            raise PilotModelError(
                f"{self.name}: cannot load model {self.path} ({type(exc).__name__}: {_first_line(exc)})"
            ) from exc
        details = interp.get_input_details()
        if len(details) == 1:
            # a dynamic batch (Keras: -1) is allocated as 1 here; make sure, before the buffers are laid out
            sig = [int(d) for d in details[0].get("shape_signature", details[0]["shape"])]
            shape = [int(d) for d in details[0]["shape"]]
            if len(shape) == 4 and sig[0] == -1 and shape[0] != 1:
                interp.resize_tensor_input(details[0]["index"], [1, *shape[1:]])
        try:
            interp.allocate_tensors()
        except Exception as exc:
            raise PilotModelError(
                f"{self.name}: cannot prepare model {self.path} ({type(exc).__name__}: {_first_line(exc)})"
            ) from exc
        return interp

    def _ordered_outputs(self) -> list[dict[str, Any]]:
        """Output details in the order to read them: the single signature's (Donkeycar's order), else the
        model's own."""
        details = self.interpreter.get_output_details()
        self._signature_names: dict[int, str] = {}
        try:
            signatures = self.interpreter.get_signature_list()
        except Exception:  # old runtimes without signatures
            signatures = {}
        if len(signatures) != 1:
            return details
        key = next(iter(signatures))
        try:
            by_name = self.interpreter.get_signature_runner(key).get_output_details()
        except Exception:
            return details
        by_index = {int(d["index"]): d for d in details}
        ordered = []
        for out_name in signatures[key].get("outputs", []):
            index = int(by_name[out_name]["index"]) if out_name in by_name else -1
            if index not in by_index:
                return details
            ordered.append(by_index[index])
            self._signature_names[index] = out_name
        return ordered if len(ordered) == len(details) else details

    def _named(self, outputs: list[dict[str, Any]]) -> list[tuple[dict[str, Any], str]]:
        return [(d, self._signature_names.get(int(d["index"]), d["name"])) for d in outputs]

    # ---------------------------------------------------------------------------------------- inference
    def _infer(self, image: np.ndarray) -> list[np.ndarray]:
        interp = self.interpreter
        with self._lock:
            if self._batch != 1:  # after infer_batch: back to one frame
                self._resize(1)
            view = interp.tensor(self._input_index)()  # the interpreter's own input buffer
            self.encoder.encode(image, view[0])
            del view  # no reference may outlive the write: invoke() refuses to run while one does
            interp.invoke()
            return [interp.get_tensor(i) for i in self._output_indices]

    def _resize(self, n: int) -> None:
        interp = self.interpreter
        shape = [int(d) for d in interp.get_input_details()[0]["shape"]]
        interp.resize_tensor_input(self._input_index, [n, *shape[1:]])
        interp.allocate_tensors()
        self._batch = n

    def infer_batch(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """The model's raw outputs for several frames in one call (the input resized to their number).

        For a model whose batch dimension is dynamic (``input_info.shape[0]`` is ``None``): a pilot server infers
        many cars' frames at once (read them with :meth:`batch_commands`). Resizing reallocates the
        interpreter's tensors, so it happens only when the number of frames changes. Frames are not checked here.
        """
        interp = self.interpreter
        n = len(images)
        with self._lock:
            if n != self._batch:
                self._resize(n)
            view = interp.tensor(self._input_index)()
            for k, img in enumerate(images):
                self.encoder.encode(img, view[k])
            del view  # invoke() refuses to run while a view of its buffers is alive
            interp.invoke()
            return [interp.get_tensor(i) for i in self._output_indices]

    def __repr__(self) -> str:
        return (
            f"<TflitePilot {self.path} {self.layout} {self.input_info.type} threads={self.num_threads} "
            f"offload={self.offload} inferences={self.inferences}>"
        )


def _info(detail: dict[str, Any], name: str | None = None) -> TensorInfo:
    """A LiteRT tensor detail → :class:`TensorInfo` (dynamic dims, ``-1`` in the signature, become ``None``)."""
    sig = detail.get("shape_signature")
    dims = sig if sig is not None and len(sig) == len(detail["shape"]) else detail["shape"]
    shape = tuple(None if int(d) < 0 else int(d) for d in dims)
    dtype = np.dtype(detail["dtype"])
    scale, zero_point = detail.get("quantization", (0.0, 0))
    usable = dtype in _TYPES and (dtype == np.float32 or scale > 0)
    return TensorInfo(
        name or detail["name"],
        shape,
        dtype.name,
        dtype if usable else None,
        float(scale),
        int(zero_point),
    )
