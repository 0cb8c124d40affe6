"""Donkeycar's ``.tflite`` pilots under ``asyncdonkey donkey``: its own ``TfLite`` interpreter, made to take
quantized models and to name the extra that provides LiteRT.

What Donkeycar does (5.3.0 and 5.4.x, ``donkeycar/utils.py`` and ``donkeycar/parts/interpreter.py``).
``manage.py drive --model pilot.tflite --type tflite_linear`` calls ``get_model_by_type``, which builds
``KerasLinear(interpreter=TfLite())``; ``TfLite.load`` takes the interpreter class from
``get_tflite_interpreter()``: 5.3.0 tries ``tflite_runtime``, then ``ai_edge_litert`` (LiteRT), then
``tensorflow.lite``; 5.4 tries LiteRT, then ``tensorflow.lite``. TensorFlow's imports are guarded in both
(``try: import tensorflow ... except ImportError``), so with LiteRT installed a ``.tflite`` pilot drives without
TensorFlow under either version. Two things go wrong all the same:

* **Quantized models fail at the first inference.** Donkeycar's own converter (``keras_to_tflite`` with a
  representative dataset, its Coral path) writes full-integer models with uint8 input and outputs, and
  ``TfLite.predict_from_dict`` casts every input to float32: LiteRT refuses it ("Cannot set tensor: Got value
  of type FLOAT32 but expected type UINT8"), the part raises on the first tick and the drive ends.
* **No runtime installed** gives Donkeycar's "Install tflite-runtime or tensorflow" (5.3), which points at a
  runtime that has no wheels for Python 3.12+ and at the framework the user meant to avoid.

The interpreter here is a subclass of Donkeycar's ``TfLite`` (so the pilot classes, ``isinstance`` checks and
everything else stay Donkeycar's), put in place only while ``get_model_by_type`` builds the pilot: a car without
a ``.tflite`` model never imports Donkeycar's interpreter module (which imports TensorFlow when installed). It
finds LiteRT as :class:`~asyncdonkey.parts.tflite_pilot.TflitePilot` does (a missing one names the ``tflite``
extra), feeds each input as its tensor's type (float32, or quantized with the tensor's scale and zero point) and
dequantizes integer outputs, so Donkeycar's ``KerasLinear`` and the other pilots read floats as they always do.
A model without signatures is left to Donkeycar's own code (5.4 reads it through the tensor API).
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from ..parts.pilot_base import PilotModelError
from ..parts.tflite_pilot import tflite_interpreter

__all__ = ["litert_tflite_class", "tflite_pilots_replaced"]

#: a tensor's type, scale and zero point (scale 0: not quantized)
_Quant = tuple[np.dtype, float, int]


@functools.cache
def litert_tflite_class() -> type:
    """The subclass of Donkeycar's ``TfLite`` described in the module docstring (built on first use: it needs
    Donkeycar)."""
    from donkeycar.parts.interpreter import TfLite

    class LiteRtTfLite(TfLite):  # type: ignore[misc,valid-type]
        """Donkeycar's ``TfLite`` on LiteRT, with quantized inputs and outputs (``asyncdonkey donkey``)."""

        def __init__(self) -> None:
            super().__init__()
            self.quantization: tuple[dict[str, _Quant], dict[str, _Quant]] = ({}, {})

        def load(self, model_path: str) -> None:
            if os.path.splitext(model_path)[1] != ".tflite":
                raise PilotModelError(f"{model_path}: a tflite_* model type needs a .tflite file")
            interpreter = tflite_interpreter()(model_path=str(model_path))
            signatures = interpreter.get_signature_list()
            if not signatures:
                super().load(model_path)  # Donkeycar's own handling (5.4: the tensor API; 5.3: an error)
                return
            key = "serving_default" if "serving_default" in signatures else next(iter(signatures))
            self.interpreter = interpreter
            self.signatures = signatures
            self.runner = interpreter.get_signature_runner(key)
            self.input_keys = list(signatures[key]["inputs"])
            self.output_keys = list(signatures[key]["outputs"])
            self.quantization = (
                {k: _quant(d) for k, d in self.runner.get_input_details().items()},
                {k: _quant(d) for k, d in self.runner.get_output_details().items()},
            )

        def predict_from_dict(self, input_dict: dict[str, Any]) -> Any:
            inputs, outputs = self.quantization
            if self.runner is None or not inputs:
                return super().predict_from_dict(input_dict)
            feed = {k: _to_tensor(np.expand_dims(v, axis=0), inputs[k]) for k, v in input_dict.items()}
            result = self.runner(**feed)
            values = [_from_tensor(result[k], outputs[k])[0] for k in self.output_keys]
            return values if len(values) > 1 else values[0]

        def __str__(self) -> str:
            return "TfLite (LiteRT, asyncdonkey)"

    return LiteRtTfLite


def _quant(detail: dict[str, Any]) -> _Quant:
    scale, zero_point = detail.get("quantization", (0.0, 0))
    return np.dtype(detail["dtype"]), float(scale), int(zero_point)


def _to_tensor(value: np.ndarray, quant: _Quant) -> np.ndarray:
    dtype, scale, zero_point = quant
    if dtype.kind in "iu" and scale > 0:
        info = np.iinfo(dtype)
        q = np.rint(np.asarray(value, np.float32) / scale + zero_point)
        return np.clip(q, info.min, info.max).astype(dtype)
    return np.asarray(value, dtype)


def _from_tensor(value: np.ndarray, quant: _Quant) -> np.ndarray:
    dtype, scale, zero_point = quant
    if dtype.kind in "iu" and scale > 0:
        return (np.asarray(value, np.float32) - zero_point) * np.float32(scale)
    return np.asarray(value)


@contextlib.contextmanager
def tflite_pilots_replaced() -> Iterator[None]:
    """Within the block, Donkeycar's ``get_model_by_type`` builds ``tflite_*`` pilots on :func:`litert_tflite_class`.

    The function is wrapped where it is looked up (``donkeycar.utils.get_model_by_type``, read at call time by
    the templates' ``dk.utils.get_model_by_type``); the wrapper swaps the interpreter class in only for the
    call, and only for ``tflite_*`` types.
    """
    import donkeycar.utils

    original: Callable[..., Any] = donkeycar.utils.get_model_by_type

    @functools.wraps(original)
    def get_model_by_type(model_type: str | None, cfg: Any) -> Any:
        kind = model_type if model_type is not None else getattr(cfg, "DEFAULT_MODEL_TYPE", "")
        if "tflite_" not in str(kind):
            return original(model_type, cfg)
        import donkeycar.parts.interpreter as interpreters

        saved = interpreters.TfLite
        interpreters.TfLite = litert_tflite_class()
        try:
            return original(model_type, cfg)
        finally:
            interpreters.TfLite = saved

    donkeycar.utils.get_model_by_type = get_model_by_type
    try:
        yield
    finally:
        donkeycar.utils.get_model_by_type = original
