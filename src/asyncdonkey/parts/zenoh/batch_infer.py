"""One model call for several cars' frames: a pilot model (ONNX or TFLite) run on a batch.

:class:`BatchPilot` loads the model through the car's own pilot parts (:func:`asyncdonkey.parts.pilot.load_pilot`),
so a model a car can run, the server can run: the same checks at load, the same preprocessing (Donkeycar's
``frame / 255``, or the quantized input's scale), the same output forms (one output of two values, two of one,
angle only), clipping and NaN checks. What it adds is the batch:

* **ONNX**: when the model's input has a dynamic batch dimension, the frames are stacked into one
  ``[n, 120, 160, 3]`` tensor and run in one ``session.run``. When the batch is fixed at 1 (the shipped
  ``sim_pilot.onnx``, and every model exported with a fixed batch), the frames are run one call each, and the
  server says so once in its log. :func:`dynamic_batch_onnx` writes a batchable copy of such a model when its
  batch of 1 is only written in its input, outputs and ``Reshape`` shapes (checked: the copy must give the
  same answers as the original on every frame of a batch, or it is not written).
* **TFLite**: a model whose input signature has a dynamic batch (``-1``: Keras' and Donkeycar's converted
  models) is resized to the batch size with ``resize_tensor_input`` (and re-allocated only when the size
  changes); a fixed batch runs one call per frame.
* **GPU** (``gpu=True``, ONNX only): onnxruntime's CUDA provider when this onnxruntime has it (the
  ``onnxruntime-gpu`` package); otherwise a warning naming the providers it has, and the CPU.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..pilot_base import PilotBase, PilotModelError, _first_line

__all__ = ["BatchPilot", "dynamic_batch_onnx"]

logger = logging.getLogger(__name__)

CUDA = "CUDAExecutionProvider"


class BatchPilot:
    """``infer(images) -> [(angle, throttle), ...]``: one call for the batch where the model allows it.

    Args:
        model_path: a ``.onnx`` or ``.tflite`` pilot.
        max_batch: the largest batch one call gets (a longer list is split).
        gpu: run an ONNX model on onnxruntime's CUDA provider when available (else a warning and the CPU).
        threads: the runtime's compute threads (default: physical cores).

        timer: what the time of a model call is read from (seconds; default ``time.perf_counter``: a call is
            real work in a worker thread, whatever clock the server's loop runs on).

    Attributes:
        batched: one call per batch (``False``: the model's batch is fixed at 1, one call per frame).
        provider: where an ONNX model runs (``CPUExecutionProvider`` or ``CUDAExecutionProvider``).
        calls: model calls made (``session.run`` / the interpreter's ``invoke``): one per batch of up to
            ``max_batch`` frames, or one per frame for a model whose batch is fixed at 1. Counted here, where
            the calls are made, because only here is it known how many one ``infer`` took.
        frames: frames inferred (over all calls; ``frames / calls`` is the mean frames per model call).
        call_s: seconds per model call, the recent 10,000 (the frames' preprocessing and the runtime's call).
    """

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        *,
        max_batch: int = 32,
        gpu: bool = False,
        threads: int | None = None,
        timer: Callable[[], float] = time.perf_counter,
    ) -> None:
        from ..pilot import load_pilot

        if max_batch < 1:
            raise ValueError(f"BatchPilot: max_batch must be >= 1, got {max_batch!r}")
        self.max_batch = int(max_batch)
        self.pilot: PilotBase = load_pilot(model_path, threads=threads, offload=False)
        self.path = Path(model_path)
        self.kind = "onnx" if self.path.suffix.lower() == ".onnx" else "tflite"
        self.provider = "CPUExecutionProvider"
        batch_dim = self.pilot.input_info.shape[0]
        self.batched = not isinstance(batch_dim, int)
        self.calls = 0
        self.frames = 0
        self.call_s: collections.deque[float] = collections.deque(maxlen=10_000)
        self._timer = timer
        self._session = getattr(self.pilot, "session", None)
        if gpu:
            self._use_gpu()
        if not self.batched:
            logger.warning(
                "pilot server: model %s has a fixed batch of 1 (input %s): one model call per frame, not one per"
                " batch%s",
                self.path,
                self.pilot.input_info.describe(),
                " (asyncdonkey.parts.zenoh.batch_infer.dynamic_batch_onnx writes a batchable copy)"
                if self.kind == "onnx"
                else "",
            )

    def _use_gpu(self) -> None:
        if self.kind != "onnx":
            logger.warning("pilot server: --gpu applies to ONNX models; %s runs on LiteRT's CPU kernels", self.path)
            return
        import onnxruntime as ort

        available = ort.get_available_providers()
        if CUDA not in available:
            logger.warning(
                "pilot server: --gpu asked, but this onnxruntime has no CUDA provider (it has %s; install"
                " onnxruntime-gpu with a matching CUDA): running on the CPU",
                ", ".join(available),
            )
            return
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(
                str(self.path), sess_options=opts, providers=[CUDA, "CPUExecutionProvider"]
            )
        except Exception as exc:
            logger.warning("pilot server: --gpu: the CUDA session failed (%s): running on the CPU", _first_line(exc))
            return
        self.provider = self._session.get_providers()[0]

    # ---------------------------------------------------------------------------------------- inference
    def infer(self, images: Sequence[np.ndarray]) -> list[tuple[float, float] | None]:
        """``(angle, throttle)`` for each frame, in order; ``None`` for a frame the model gave NaN for (logged).

        Frames must be the pilot's ``image_shape`` uint8 RGB (``ValueError`` naming the shape otherwise)."""
        shape = self.pilot.image_shape
        for img in images:
            if not isinstance(img, np.ndarray) or img.shape != shape or img.dtype != np.uint8:
                got = f"{img.shape} {img.dtype}" if isinstance(img, np.ndarray) else type(img).__name__
                raise ValueError(f"{self.pilot.name}: a frame is {got}; expected {shape} uint8 RGB")
        out: list[tuple[float, float] | None] = []
        step = self.max_batch if self.batched else 1
        for i in range(0, len(images), step):
            chunk = images[i : i + step]
            t0 = self._timer()
            raw = self._run(chunk)
            self.call_s.append(self._timer() - t0)
            self.calls += 1
            self.frames += len(chunk)
            out.extend(self._commands(raw, len(chunk)))
        return out

    def warm_up(self) -> None:
        """One call of the runtime on a blank frame, not counted in ``calls``, ``frames`` or ``call_s``: a runtime's
        first call allocates and can take many times a normal one, and a server that makes it before it answers
        (:class:`.PilotServer` in a pair) must not report it as a model call of its cars."""
        self._run([np.zeros(self.pilot.image_shape, np.uint8)])

    def _run(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        if self.kind == "onnx":
            return self._run_onnx(images)
        return self._run_tflite(images)

    def _run_onnx(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        p = self.pilot
        h, w, c = p.image_shape
        buf = np.empty((len(images), h, w, c) if p.layout == "NHWC" else (len(images), c, h, w), np.float32)
        for k, img in enumerate(images):
            p.encoder.encode(img, buf[k])
        return self._session.run(None, {p.input_info.name: buf})  # type: ignore[union-attr]

    def _run_tflite(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        return self.pilot.infer_batch(images)  # type: ignore[attr-defined]

    def _commands(self, raw: list[np.ndarray], n: int) -> list[tuple[float, float] | None]:
        """The batch's raw outputs → one command per frame, read as the pilot reads its own."""
        angles, throttles = self.pilot.batch_commands(raw, n)
        out: list[tuple[float, float] | None] = []
        for a, t in zip(angles.tolist(), throttles.tolist(), strict=True):
            if math.isnan(a) or math.isnan(t):
                logger.warning(
                    "pilot server: model %s produced NaN (angle %s, throttle %s): no command", self.path, a, t
                )
                out.append(None)
                continue
            out.append((min(1.0, max(-1.0, a)), min(1.0, max(-1.0, t))))
        return out

    def __repr__(self) -> str:
        how = f"batches of up to {self.max_batch}" if self.batched else "one frame per call"
        return f"<BatchPilot {self.path} {self.kind} {self.provider} {how}>"


def dynamic_batch_onnx(src: str | os.PathLike[str], dst: str | os.PathLike[str], *, check: int = 3) -> Path:
    """Write a copy of the ONNX pilot ``src`` whose batch dimension is dynamic, to ``dst``.

    The batch of 1 is replaced in the graph's input and outputs (by the symbol ``batch``) and in the leading
    ``1`` of constant ``Reshape`` shapes (by ``-1``): that is where exporters of Donkeycar-style pilots write it.
    The copy is then run on a batch of ``check`` random frames and must answer each as the original answers it
    alone (to 1e-5); otherwise :class:`PilotModelError` and nothing is written. Needs the ``onnx`` package.
    """
    import onnx
    import onnxruntime as ort
    from onnx import numpy_helper

    src, dst = Path(src), Path(dst)
    model = onnx.load(str(src))
    graph = model.graph
    for value in [*graph.input, *graph.output]:
        dims = value.type.tensor_type.shape.dim
        if dims and dims[0].HasField("dim_value") and dims[0].dim_value == 1:
            dims[0].dim_param = "batch"
    reshape_shapes = {n.input[1] for n in graph.node if n.op_type == "Reshape" and len(n.input) > 1}
    for k, init in enumerate(graph.initializer):
        if init.name in reshape_shapes:
            shape = numpy_helper.to_array(init).copy()
            if shape.ndim == 1 and len(shape) and shape[0] == 1:
                shape[0] = -1
                graph.initializer[k].CopyFrom(numpy_helper.from_array(shape, init.name))
    data = model.SerializeToString()
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    try:
        one = ort.InferenceSession(str(src), sess_options=opts, providers=["CPUExecutionProvider"])
        many = ort.InferenceSession(data, sess_options=opts, providers=["CPUExecutionProvider"])
        name = one.get_inputs()[0].name
        shape = [int(d) for d in one.get_inputs()[0].shape[1:]]
        batch = np.random.default_rng(0).random((check, *shape), dtype=np.float32)
        together = [np.asarray(o).reshape(check, -1) for o in many.run(None, {name: batch})]
        for k in range(check):
            alone = [np.asarray(o).reshape(1, -1) for o in one.run(None, {name: batch[k : k + 1]})]
            if not all(np.allclose(a[0], t[k], atol=1e-5) for a, t in zip(alone, together, strict=True)):
                raise PilotModelError(f"dynamic_batch_onnx: {src}: frame {k} of a batch answers differently alone")
    except PilotModelError:
        raise
    except Exception as exc:
        raise PilotModelError(
            f"dynamic_batch_onnx: {src}: the batch of 1 is written elsewhere in the graph than its input, outputs"
            f" and Reshape shapes ({type(exc).__name__}: {_first_line(exc)})"
        ) from exc
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_bytes(data)
    return dst
