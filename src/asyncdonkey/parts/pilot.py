"""ONNX autopilot: a Donkeycar-style image → (angle, throttle) model run with onnxruntime on the CPU.

Usage, as Donkeycar wires its pilot::

    v.add(OnnxPilot("models/pilot.onnx"), inputs=["cam/image_array"],
          outputs=["pilot/angle", "pilot/throttle"], run_condition="run_pilot")

Design notes:

* **Off the loop thread.** ``run()`` is ``async``: inference runs in a single-thread executor owned by the
  pilot, so serial readers, pollers and web clients keep being served while it computes, and the tick still
  awaits the result in order. One thread, because one session and one frame at a time is all a drive loop
  needs, and it keeps onnxruntime's own threads the only parallelism (``offload=False`` runs inline).
* **Low-latency session.** Intra-op threads = physical cores (hyper-threads only contend for the same
  units), thread spinning off (``session.intra_op.allow_spinning = "0"``: spinning workers would burn the
  cores the rest of the car needs between frames at 20 Hz), sequential execution (a pilot graph is a chain;
  the parallel executor only adds scheduling), all graph optimisations on, CPU provider.
* **Checked at load, not on the first tick.** The file must exist and parse; the input must be a 4-D float
  image of the configured shape in NHWC or NCHW with batch 1 or dynamic; the outputs must be one of the
  forms below. One inference on a blank frame at load checks the real output sizes and warms the session.
* **Preprocessing as Donkeycar's:** uint8 RGB → float32 / 255, a batch of one (transposed for NCHW).

Supported outputs: one output with two values ``[angle, throttle]``; two outputs of one value each (angle
first, unless they are named ``angle`` and ``throttle``, which then decide); one output with one value
(angle only; the throttle is the constant ``default_throttle``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import math
import os
import threading
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ..errors import AsyncdonkeyError

__all__ = ["OnnxPilot", "PilotModelError", "physical_cores"]

IMAGE_SHAPE = (120, 160, 3)


class PilotModelError(AsyncdonkeyError, ValueError):
    """The model file is missing, unreadable or not a pilot this part can run; the message names the file."""


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


class OnnxPilot:
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
        self.path = Path(model_path)
        self.name = name or f"OnnxPilot({self.path.name})"
        self.image_shape = tuple(int(d) for d in image_shape)
        if len(self.image_shape) != 3 or self.image_shape[2] != 3:
            raise ValueError(f"{self.name}: image_shape must be (rows, columns, 3), got {image_shape!r}")
        if intra_op_threads is not None and (not isinstance(intra_op_threads, int) or intra_op_threads < 1):
            raise ValueError(f"{self.name}: intra_op_threads must be a positive int, got {intra_op_threads!r}")
        self.intra_op_threads = intra_op_threads or physical_cores()
        self.offload = bool(offload)
        self.inferences = 0
        self.last_inference_s = math.nan
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._local = threading.local()
        self._closed = False

        self.session = self._load()
        self.input_name, self.layout = self._check_input()
        self._output_plan = self._check_outputs()
        self._output_names = [o.name for o in self.session.get_outputs()]
        self._warm_up()
        if self._output_plan == "angle" and default_throttle is None:
            raise PilotModelError(
                f"{self.name}: model {self.path} outputs the angle only; pass default_throttle= for the throttle"
            )
        self.default_throttle = None if default_throttle is None else float(default_throttle)

    # ------------------------------------------------------------------------------------------ loading
    def _load(self) -> Any:
        import onnxruntime as ort

        if not self.path.is_file():
            raise PilotModelError(f"{self.name}: model file {self.path} does not exist")
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

    def _check_input(self) -> tuple[str, Literal["NHWC", "NCHW"]]:
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise PilotModelError(
                f"{self.name}: model {self.path} has {len(inputs)} inputs {[i.name for i in inputs]}; "
                "a pilot takes one image"
            )
        inp = inputs[0]
        shape = list(inp.shape)
        if inp.type != "tensor(float)" or len(shape) != 4:
            raise PilotModelError(
                f"{self.name}: model {self.path} input {inp.name!r} is {inp.type} {_fmt(shape)}; "
                f"expected a 4-D float tensor (batch, image)"
            )
        batch = shape[0]
        if isinstance(batch, int) and batch != 1:
            raise PilotModelError(
                f"{self.name}: model {self.path} input {inp.name!r} has batch {batch}; expected 1 or dynamic"
            )
        h, w, c = self.image_shape
        nhwc, nchw = [h, w, c], [c, h, w]
        dims = shape[1:]
        if _matches(dims, nhwc):
            layout: Literal["NHWC", "NCHW"] = "NHWC"
        elif _matches(dims, nchw):
            layout = "NCHW"
        else:
            raise PilotModelError(
                f"{self.name}: model {self.path} wants input {inp.name!r} {_fmt(shape)}, but frames are "
                f"{h}x{w}x{c} (expected [1, {h}, {w}, {c}] NHWC or [1, {c}, {h}, {w}] NCHW; image_shape="
                f"{self.image_shape})"
            )
        return inp.name, layout

    def _check_outputs(self) -> Literal["pair", "two", "angle"]:
        outs = self.session.get_outputs()
        sizes = [_static_size(o.shape) for o in outs]
        desc = ", ".join(f"{o.name!r} {o.type} {_fmt(o.shape)}" for o in outs)
        bad = PilotModelError(
            f"{self.name}: model {self.path} outputs {desc}; expected one output of 2 values (angle, throttle), "
            "two outputs of 1 value (angle, throttle) or one output of 1 value (angle)"
        )
        if any(o.type != "tensor(float)" for o in outs):
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
        outs = self.session.run(None, {self.input_name: self._preprocess(np.zeros(self.image_shape, np.uint8))})
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
        names = [n.lower() for n in self._output_names]
        self._swap = plan == "two" and names == ["throttle", "angle"]

    # ---------------------------------------------------------------------------------------- inference
    def _preprocess(self, image: np.ndarray) -> np.ndarray:
        """uint8 frame → float32 ``/ 255`` batch of one in the model's layout, in one pass.

        The result goes into a buffer kept per thread: a fresh 230 kB array per frame is a fresh mmap for
        the allocator, and its page faults cost more than the division. Each thread reuses its own buffer,
        and ``session.run`` has copied it by the time it returns."""
        buf = getattr(self._local, "buf", None)
        if buf is None:
            h, w, c = self.image_shape
            buf = self._local.buf = np.empty((1, h, w, c) if self.layout == "NHWC" else (1, c, h, w), np.float32)
        src = image if self.layout == "NHWC" else image.transpose(2, 0, 1)
        np.divide(src, np.float32(255.0), out=buf[0], dtype=np.float32)
        return buf

    def predict(self, image: np.ndarray) -> tuple[float, float]:
        """One frame (``image_shape`` uint8 RGB) → ``(angle, throttle)``, each clipped to ``[-1, 1]``.

        Synchronous: for replay, tests and the executor. Raises ``ValueError`` naming the part for a frame of
        the wrong shape or type, or when the model produces NaN.
        """
        if not isinstance(image, np.ndarray) or image.shape != self.image_shape or image.dtype != np.uint8:
            got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else f"a {type(image).__name__}"
            raise ValueError(f"{self.name}: cam/image_array frame is {got}; expected {self.image_shape} uint8 RGB")
        t0 = time.perf_counter()
        outs = self.session.run(None, {self.input_name: self._preprocess(image)})
        plan = self._output_plan
        if plan == "pair":
            angle, throttle = np.ravel(outs[0])
        elif plan == "two":
            angle, throttle = float(np.ravel(outs[0])[0]), float(np.ravel(outs[1])[0])
            if self._swap:
                angle, throttle = throttle, angle
        else:
            angle, throttle = float(np.ravel(outs[0])[0]), self.default_throttle
        angle, throttle = float(angle), float(throttle)
        if math.isnan(angle) or math.isnan(throttle):
            raise ValueError(f"{self.name}: model {self.path} produced NaN (angle {angle}, throttle {throttle})")
        self.last_inference_s = time.perf_counter() - t0
        self.inferences += 1
        return _clip(angle), _clip(throttle)

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
            self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="onnx-pilot")
        return await asyncio.get_running_loop().run_in_executor(self._executor, self.predict, image)

    def shutdown(self) -> None:
        """Release the worker thread (waits for an inference in progress)."""
        self._closed = True
        ex, self._executor = self._executor, None
        if ex is not None:
            ex.shutdown(wait=True)

    def __repr__(self) -> str:
        return (
            f"<OnnxPilot {self.path} {self.layout} threads={self.intra_op_threads} "
            f"offload={self.offload} inferences={self.inferences}>"
        )


def _matches(dims: list[Any], want: list[int]) -> bool:
    """Static dims must equal ``want``; symbolic (named or unknown) dims accept any size."""
    return all(not isinstance(d, int) or d == w for d, w in zip(dims, want, strict=True))


def _static_size(shape: list[Any]) -> int | None:
    """Values per batch item when every non-batch dim is static, else ``None`` (the batch dim is ignored
    when the output is at least 2-D)."""
    dims = shape[1:] if len(shape) >= 2 else shape
    if not all(isinstance(d, int) for d in dims):
        return None
    return int(np.prod(dims)) if dims else 1


def _fmt(shape: Any) -> str:
    return "[" + ", ".join(str(d) if d is not None else "?" for d in shape) + "]"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:300] if text else "no message"


def _clip(v: float) -> float:
    return -1.0 if v < -1.0 else (1.0 if v > 1.0 else v)
