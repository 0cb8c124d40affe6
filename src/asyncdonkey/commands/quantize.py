"""``asyncdonkey quantize``: an INT8 copy of an ONNX pilot, calibrated on the car's own frames from a tub.

::

    asyncdonkey quantize models/pilot.onnx --tub data/tub --out models/pilot.int8.onnx

    report = quantize_pilot("models/pilot.onnx", "data/tub", "models/pilot.int8.onnx")
    report.angle_diff_mean, report.float_ms, report.int8_ms

Static quantization needs the range of every activation, measured on inputs like the real ones: here frames
read from a tub (spread evenly over it) and prepared exactly as the pilot prepares them when it drives (the same
:class:`~asyncdonkey.parts.pilot.OnnxPilot` preprocessing, ``/ 255`` in the model's layout), so the quantized
model is calibrated on what the car's camera sees. The quantization itself is onnxruntime's
(:func:`onnxruntime.quantization.quantize_static`), in QDQ form: the model keeps its float32 input and outputs
and carries QuantizeLinear/DequantizeLinear pairs that onnxruntime fuses into integer kernels, so
:class:`~asyncdonkey.parts.pilot.OnnxPilot` runs the result unchanged. Weights are int8 per output channel by
default (per-tensor weights lose more on convolutions whose filters differ in scale), activations int8.

After writing, the INT8 model is loaded as a pilot (the same load-time checks as any model) and both models run
on the calibration frames: the report gives how far the INT8 answers are from the float ones and what each costs
here. Whether INT8 pays depends on the model and the CPU: see ``benchmarks/pilot.py`` and docs/pilot.md.

Needs the ``onnx`` package (onnxruntime's quantization tools use it): the ``quantize`` extra (``docs/install.md``).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AsyncdonkeyError
from ..extras import require
from ..parts.tub import Tub, TubError, TubImageError

__all__ = ["METHODS", "QuantizeError", "QuantizeReport", "add_quantize_parser", "quantize_main", "quantize_pilot"]

EXIT_USAGE = 2
#: Mean angle difference (INT8 vs float) above which the report warns: a tenth of a typical turn.
WARN_ANGLE_DIFF = 0.05
#: Calibration methods: onnxruntime's ``CalibrationMethod`` names.
METHODS = {"minmax": "MinMax", "entropy": "Entropy", "percentile": "Percentile"}


class QuantizeError(AsyncdonkeyError):
    """Quantization cannot run; the message is one line naming the model, tub or output file."""


@dataclass
class QuantizeReport:
    """What :func:`quantize_pilot` did and measured (differences and times over the calibration frames)."""

    model: str
    out: str
    tub: str
    frames: int
    """calibration frames read from the tub."""
    method: str
    per_channel: bool
    float_bytes: int
    int8_bytes: int
    angle_diff_mean: float
    """mean ``|int8 angle - float angle|`` over the calibration frames (both clipped to [-1, 1])."""
    angle_diff_max: float
    throttle_diff_mean: float
    throttle_diff_max: float
    float_ms: float
    """median ``predict()`` time of the float model on the frames, ms."""
    int8_ms: float
    seconds: float
    """wall-clock time of the whole quantization."""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def format_table(self) -> str:
        speed = self.float_ms / self.int8_ms if self.int8_ms > 0 else float("nan")
        lines = [
            f"wrote {self.out} ({self.int8_bytes:,} bytes; float32 model {self.float_bytes:,} bytes)",
            f"calibrated on  {self.frames} frames of {self.tub} ({self.method}, "
            f"{'per-channel' if self.per_channel else 'per-tensor'} weights) in {self.seconds:.1f} s",
            f"INT8 vs float  angle |diff| mean {self.angle_diff_mean:.4f} max {self.angle_diff_max:.4f}; "
            f"throttle mean {self.throttle_diff_mean:.4f} max {self.throttle_diff_max:.4f}",
            f"predict()      float32 {self.float_ms:.3f} ms, INT8 {self.int8_ms:.3f} ms (median) "
            f"= {speed:.2f}x {'faster' if speed >= 1 else 'slower'} on this machine",
        ]
        if self.angle_diff_mean > WARN_ANGLE_DIFF:
            lines.append(
                f"warning: the INT8 angle is {self.angle_diff_mean:.3f} off the float one on average: "
                "this model loses too much in 8 bits; drive on the float model (or replay both to compare)"
            )
        return "\n".join(lines)


def tub_frames(tub_path: str | os.PathLike[str], count: int, image_key: str = "cam/image_array") -> list[np.ndarray]:
    """Up to ``count`` readable ``image_key`` frames spread evenly over the tub (all of them if it has fewer).

    Raises :class:`QuantizeError` when the tub records no such images or none can be read, and the tub's own
    errors (:class:`~asyncdonkey.parts.tub.TubError`) for a missing tub or not a tub."""
    tub = Tub(tub_path)
    if image_key not in tub.inputs:
        raise QuantizeError(f"{tub.base_path}: the tub records no {image_key} (it records {tub.inputs})")
    records = [r for r in tub.records() if r.raw.get(image_key) is not None]
    if count < len(records):
        picks = sorted(set(np.linspace(0, len(records) - 1, count).round().astype(int).tolist()))
        records = [records[i] for i in picks]
    frames = []
    for rec in records:
        try:
            image = rec[image_key]
        except TubImageError:  # an unreadable frame is passed over; a name leading out of the tub stops
            continue
        if isinstance(image, np.ndarray) and image.dtype == np.uint8 and image.ndim == 3:
            frames.append(image)
    if not frames:
        raise QuantizeError(f"{tub.base_path}: no readable {image_key} frame to calibrate on")
    return frames


class _TubReader:
    """onnxruntime's ``CalibrationDataReader`` protocol: one input feed per frame, then ``None``."""

    def __init__(self, pilot: Any, frames: list[np.ndarray]) -> None:
        self._feeds = iter([{pilot.input_name: pilot._preprocess(f).copy()} for f in frames])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._feeds, None)


def quantize_pilot(
    model: str | os.PathLike[str],
    tub: str | os.PathLike[str],
    out: str | os.PathLike[str] | None = None,
    *,
    frames: int = 200,
    method: str = "minmax",
    per_channel: bool = True,
    image_key: str = "cam/image_array",
) -> QuantizeReport:
    """Write an INT8 (QDQ) copy of the ONNX pilot ``model`` calibrated on up to ``frames`` frames of ``tub``.

    ``out`` defaults to ``<model>.int8.onnx`` beside the model. ``method``: one of :data:`METHODS`. Raises
    :class:`QuantizeError` (bad model, no frames, unwritable output), :class:`~asyncdonkey.parts.tub.TubError`
    for the tub, and :class:`~asyncdonkey.extras.MissingExtra` naming the ``quantize`` extra when ``onnx`` is
    missing.
    """
    from ..parts.pilot import OnnxPilot, PilotModelError

    t_start = time.perf_counter()
    model_path = Path(model)
    out_path = Path(out) if out is not None else model_path.with_name(model_path.stem + ".int8.onnx")
    if method not in METHODS:
        raise ValueError(f"quantize: method must be one of {sorted(METHODS)}, got {method!r}")
    if not isinstance(frames, int) or frames < 1:
        raise ValueError(f"quantize: frames must be a positive int, got {frames!r}")
    if model_path.suffix.lower() != ".onnx":
        raise QuantizeError(
            f"model {model_path}: quantize takes an ONNX model (.onnx); TFLite models are "
            "quantized when they are converted (see docs/pilot.md)"
        )
    if out_path.resolve() == model_path.resolve():
        raise QuantizeError(f"--out {out_path} is the model itself; choose another file")
    if not out_path.absolute().parent.is_dir():
        raise QuantizeError(f"cannot write {out_path}: its directory does not exist")
    require("onnx", "quantize", "asyncdonkey quantize")  # onnxruntime's quantization tools import it
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    images = tub_frames(tub, frames, image_key)
    try:
        float_pilot = OnnxPilot(model_path, offload=False, image_shape=images[0].shape)
    except PilotModelError as exc:
        raise QuantizeError(str(exc)) from exc

    ort_logger = logging.getLogger()  # onnxruntime.quantization logs on the root logger
    with tempfile.TemporaryDirectory(prefix="asyncdonkey-quantize-") as tmp:
        tmp_out = Path(tmp) / "int8.onnx"
        level = ort_logger.level
        ort_logger.setLevel(logging.ERROR)  # its advice (run quant_pre_process, ...) is not the user's business
        try:
            quantize_static(
                str(model_path),
                str(tmp_out),
                _TubReader(float_pilot, images),
                quant_format=QuantFormat.QDQ,
                per_channel=per_channel,
                activation_type=QuantType.QInt8,
                weight_type=QuantType.QInt8,
                calibrate_method=getattr(CalibrationMethod, METHODS[method]),
                calibration_providers=["CPUExecutionProvider"],
            )
        except Exception as exc:
            raise QuantizeError(f"cannot quantize {model_path}: {type(exc).__name__}: {exc}") from exc
        finally:
            ort_logger.setLevel(level)
        staged = out_path.with_name(out_path.name + ".tmp")
        staged.write_bytes(tmp_out.read_bytes())
    try:
        int8_pilot = OnnxPilot(staged, offload=False, image_shape=images[0].shape, name=f"OnnxPilot({out_path.name})")
    except PilotModelError as exc:
        staged.unlink(missing_ok=True)
        raise QuantizeError(f"the quantized model does not load as a pilot: {exc}") from exc
    os.replace(staged, out_path)

    diffs, t_float, t_int8 = [], [], []
    for image in images:
        a = float_pilot.predict(image)
        t_float.append(float_pilot.last_inference_s)
        b = int8_pilot.predict(image)
        t_int8.append(int8_pilot.last_inference_s)
        diffs.append((abs(a[0] - b[0]), abs(a[1] - b[1])))
    d = np.array(diffs)
    return QuantizeReport(
        model=str(model_path),
        out=str(out_path),
        tub=str(tub),
        frames=len(images),
        method=method,
        per_channel=per_channel,
        float_bytes=model_path.stat().st_size,
        int8_bytes=out_path.stat().st_size,
        angle_diff_mean=float(d[:, 0].mean()),
        angle_diff_max=float(d[:, 0].max()),
        throttle_diff_mean=float(d[:, 1].mean()),
        throttle_diff_max=float(d[:, 1].max()),
        float_ms=float(np.median(t_float) * 1e3),
        int8_ms=float(np.median(t_int8) * 1e3),
        seconds=time.perf_counter() - t_start,
    )


# ----------------------------------------------------------------------------------------------- CLI
def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def add_quantize_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``quantize`` subcommand to the ``asyncdonkey`` parser's subparsers."""
    p = subparsers.add_parser(
        "quantize",
        help="write an INT8 copy of an ONNX pilot, calibrated on a tub's frames",
        description="Quantize an ONNX pilot to INT8 (onnxruntime's static quantization, QDQ form) with frames "
        "from a tub as calibration data, then compare the INT8 model with the float one on those frames.",
    )
    p.add_argument("model", help="the float32 ONNX pilot (.onnx), e.g. models/pilot.onnx")
    p.add_argument(
        "--tub",
        required=True,
        metavar="TUB",
        help="a tub directory recorded by the car, whose frames calibrate the model, e.g. data/tub",
    )
    p.add_argument(
        "--out", default=None, metavar="FILE", help="the INT8 .onnx model to write (default: MODEL with .int8.onnx)"
    )
    p.add_argument(
        "--frames",
        type=_positive_int,
        default=200,
        metavar="N",
        help="calibration frames spread over the tub, at least 1 (default: %(default)s)",
    )
    p.add_argument(
        "--method", choices=sorted(METHODS), default="minmax", help="calibration method (default: %(default)s)"
    )
    p.add_argument("--per-tensor", action="store_true", help="one weight scale per tensor, not per channel")
    p.add_argument(
        "--image-key",
        default="cam/image_array",
        metavar="CHANNEL",
        help="the tub's camera channel (default: %(default)s)",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    p.set_defaults(handler=quantize_main)
    return p


def quantize_main(args: argparse.Namespace) -> int:
    """Run ``asyncdonkey quantize``; errors print one line and return 2."""
    from .recordings import check_tub_directory

    try:
        check_tub_directory(args.tub, "--tub")
        report = quantize_pilot(
            args.model,
            args.tub,
            args.out,
            frames=args.frames,
            method=args.method,
            per_channel=not args.per_tensor,
            image_key=args.image_key,
        )
    except (QuantizeError, TubError, OSError, ImportError) as exc:
        print(f"asyncdonkey quantize: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(json.dumps(report.as_dict(), indent=2) if args.json else report.format_table())
    return 0
