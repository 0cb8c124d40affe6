"""Pilot inference: ONNX and TFLite, float32 and INT8, what each costs and what INT8 costs in accuracy.

Two models, each in four forms:

* **Donkeycar-shaped CNN**: the layers of Donkeycar's ``KerasLinear`` (five convolutions, two dense layers,
  seeded random weights; about a millisecond of compute). ONNX float32 from
  :func:`~asyncdonkey.pilot_export.export_donkey_linear_shaped`; ONNX INT8 from ``asyncdonkey quantize``
  (:func:`~asyncdonkey.commands.quantize.quantize_pilot`) calibrated on a simulator tub; TFLite float32 and full-integer
  INT8 with the same weights, built with TensorFlow by ``examples/make_tflite_models.py --bench`` into
  ``benchmarks/models/`` (3.3 MB, not committed: without TensorFlow those rows say so).
* **Simulator pilot** (``examples/models/sim_pilot.onnx``, linear on 800 features; a tenth of the CNN's
  compute): the committed ONNX and TFLite files, and its ONNX INT8 quantized here the same way.

For each form, per inference, median and p99 latency of:

* **bare**: the runtime's own call on an input already prepared: ``session.run`` (onnxruntime) or ``invoke()`` +
  reading the outputs (LiteRT), the pilot's own session/interpreter, so thread settings are identical;
* **predict()**: the pilot part on the uint8 frame: checks, Donkeycar's ``/ 255`` (or quantization of the frame),
  the inference, unpacking, dequantization, clipping. The overhead is ``predict / bare - 1`` on medians (target
  <= 5 % on the Donkeycar-shaped model);
* **run() in a tick**: the part's time in a Vehicle's profiler, ``run()`` awaited through the pilot's worker
  thread, flat out on uvloop; and **at 20 Hz**, where every inference starts after 50 ms idle (cold caches,
  sleeping threads): what a car sees.

bare and predict() alternate call by call, so drifts of the machine hit both alike.

Accuracy: every form replays the same simulator tub (a scripted driver's lap, recorded here; the INT8 ONNX
models are calibrated on another one) through ``asyncdonkey replay``: the angle MAE against the driver, and the
mean ``|angle - float32 angle|`` of the same runtime (what quantization changed). The CNN's random weights do not
steer, so its MAE against the driver means nothing; its difference from float32 does.

    python benchmarks/pilot.py            # about two minutes
    python benchmarks/pilot.py --quick    # about 20 s
    python benchmarks/pilot.py --json     # figures as JSON
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking
from asyncdonkey.parts.pilot import OnnxPilot, PilotBase, load_pilot
from asyncdonkey.pilot_export import export_donkey_linear_shaped
from machine_info import describe

TARGET_OVERHEAD_PCT = 5.0
ROOT = Path(__file__).resolve().parents[1]
SIM_MODELS = ROOT / "examples" / "models"
BENCH_MODELS = Path(__file__).resolve().parent / "models"
FORMS = ("ONNX float32", "ONNX INT8", "TFLite float32", "TFLite INT8")


def camera_frame() -> np.ndarray:
    from asyncdonkey.parts.sim import Simulator

    return Simulator().render()


def record_tub(path: Path, frames: int, seed: int) -> Path:
    """A scripted driver's drive in the simulator, one frame every 50 ms of simulated time, as a tub."""
    from asyncdonkey.parts.sim import ScriptedDriver, Simulator
    from asyncdonkey.parts.tub import TubWriter

    sim = Simulator()
    sim.reset(s=float(seed))
    driver = ScriptedDriver(sim.track, seed=seed)
    writer = TubWriter(
        path,
        inputs=["cam/image_array", "user/angle", "user/throttle"],
        types=["image_array", "float", "float"],
        queue_size=frames + 1,
        fsync=False,
    )
    for _ in range(frames):
        tel = sim.telemetry()
        image = sim.render()
        angle, throttle = driver.run(tel.x, tel.y, tel.heading)
        writer.run(image, angle, throttle)
        sim.step(0.05, angle, throttle)
    writer.shutdown()
    return path


def _ms(samples: list[float] | np.ndarray) -> dict[str, float]:
    ms = np.asarray(samples) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "n": len(ms)}


def bare_call(pilot: PilotBase, image: np.ndarray) -> Callable[[], Any]:
    """The runtime's own call on the frame already prepared in the pilot's session or interpreter."""
    if isinstance(pilot, OnnxPilot):
        sess, feed = pilot.session, {pilot.input_name: pilot._preprocess(image).copy()}
        return lambda: sess.run(None, feed)
    interp, outs = pilot.interpreter, pilot._output_indices  # type: ignore[attr-defined]
    pilot.predict(image)  # leaves the encoded frame in the interpreter's input buffer
    return lambda: (interp.invoke(), [interp.get_tensor(i) for i in outs])


def bare_and_predict(pilot: PilotBase, image: np.ndarray, calls: int) -> tuple[dict, dict]:
    """Per call, in turn: the bare runtime call, then ``predict()``."""
    bare_fn = bare_call(pilot, image)
    perf = time.perf_counter
    bare = np.empty(calls)
    pred = np.empty(calls)
    for _ in range(20):  # warm both paths
        bare_fn()
        pilot.predict(image)
    for i in range(calls):
        a = perf()
        bare_fn()
        b = perf()
        pilot.predict(image)
        c = perf()
        bare[i], pred[i] = b - a, c - b
    return _ms(bare), _ms(pred)


class Camera:
    def __init__(self, image: np.ndarray) -> None:
        self.image = image

    def run(self) -> np.ndarray:
        return self.image


def in_tick(path: Path, image: np.ndarray, rate_hz: float, ticks: int) -> dict:
    """The pilot part's time per tick from the Vehicle's profiler (first and last samples dropped)."""
    pilot = load_pilot(path)
    v = Vehicle(profiler_window=ticks + 2)
    v.add(Camera(image), outputs=["cam/image_array"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], name="pilot")
    run_blocking(v.run(rate_hz, ticks))
    return _ms(v.profiler.series_for("pilot").recent())


def measure_form(form: str, path: Path | None, image: np.ndarray, tub: Path, quick: bool) -> dict[str, Any]:
    if path is None or not path.is_file():
        return {
            "form": form,
            "missing": f"no {path.name if path else 'model'}: run examples/make_tflite_models.py "
            "--bench where TensorFlow installs",
        }
    from asyncdonkey.commands.replay import replay

    pilot = load_pilot(path, offload=False)
    bare, pred = bare_and_predict(pilot, image, 400 if quick else 2000)
    flat = in_tick(path, image, 1e6, 300 if quick else 2000)
    paced = in_tick(path, image, 20.0, 30 if quick else 200)
    rep = replay(tub, path)
    angles = np.array([r.pilot_angle for r in rep.rows])
    return {
        "form": form,
        "file_bytes": path.stat().st_size,
        "input": pilot.input_info.type,
        "bare": bare,
        "predict": pred,
        "run_in_tick": flat,
        "run_at_20hz": paced,
        "predict_overhead_pct": (pred["p50_ms"] / bare["p50_ms"] - 1) * 100,
        "replay_angle_mae": rep.angle_mae,
        "replay_throttle_mae": rep.throttle_mae,
        "_angles": angles,
    }


def measure_model(label: str, paths: dict[str, Path | None], image: np.ndarray, tub: Path, quick: bool) -> dict:
    forms = [measure_form(form, paths.get(form), image, tub, quick) for form in FORMS]
    by_form = {f["form"]: f for f in forms}
    for f in forms:  # what quantization changed: the INT8 angles against the float32 ones of the same runtime
        base = by_form.get(f["form"].replace("INT8", "float32"), {})
        if "_angles" in f and "_angles" in base:
            f["angle_diff_vs_float32"] = float(np.mean(np.abs(f["_angles"] - base["_angles"])))
    for f in forms:
        f.pop("_angles", None)
    return {"model": label, "forms": forms}


def measure(quick: bool) -> dict:
    from asyncdonkey.commands.quantize import quantize_pilot

    image = camera_frame()
    with tempfile.TemporaryDirectory(prefix="pilot-bench-") as tmp:
        t = Path(tmp)
        calib = record_tub(t / "calibration", 200, seed=11)
        tub = record_tub(t / "drive", 200 if quick else 600, seed=3)
        donkey = export_donkey_linear_shaped(t / "donkey_linear.onnx")
        sim = SIM_MODELS / "sim_pilot.onnx"
        frames = 50 if quick else 200
        models = [
            (
                "Donkeycar-shaped CNN",
                {
                    "ONNX float32": donkey,
                    "ONNX INT8": Path(quantize_pilot(donkey, calib, t / "donkey.int8.onnx", frames=frames).out),
                    "TFLite float32": BENCH_MODELS / "donkey_linear.tflite",
                    "TFLite INT8": BENCH_MODELS / "donkey_linear.int8.tflite",
                },
            ),
            (
                "sim_pilot (linear)",
                {
                    "ONNX float32": sim,
                    "ONNX INT8": Path(quantize_pilot(sim, calib, t / "sim.int8.onnx", frames=frames).out),
                    "TFLite float32": SIM_MODELS / "sim_pilot.tflite",
                    "TFLite INT8": SIM_MODELS / "sim_pilot.int8.tflite",
                },
            ),
        ]
        results = [measure_model(label, paths, image, tub, quick) for label, paths in models]
    first = results[0]["forms"][0]
    return {
        "machine": describe(),
        "quick": quick,
        "models": results,
        "target_overhead_pct": TARGET_OVERHEAD_PCT,
        "meets_target": first["predict_overhead_pct"] <= TARGET_OVERHEAD_PCT,
    }


def _f(x: float | None, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def table(results: dict) -> str:
    pt = PrettyTable()
    pt.field_names = [
        "model",
        "form",
        "bare p50/p99",
        "predict() p50/p99",
        "overhead",
        "run() flat p50",
        "run() 20 Hz p50/p99",
        "replay MAE",
        "|Δ| vs float",
    ]
    for m in results["models"]:
        for i, f in enumerate(m["forms"]):
            name = m["model"] if i == 0 else ""
            if "missing" in f:
                pt.add_row([name, f["form"], f["missing"], "", "", "", "", "", ""])
                continue
            pt.add_row(
                [
                    name,
                    f["form"],
                    f"{_f(f['bare']['p50_ms'])} / {_f(f['bare']['p99_ms'])}",
                    f"{_f(f['predict']['p50_ms'])} / {_f(f['predict']['p99_ms'])}",
                    f"{f['predict_overhead_pct']:+.1f} %",
                    _f(f["run_in_tick"]["p50_ms"]),
                    f"{_f(f['run_at_20hz']['p50_ms'])} / {_f(f['run_at_20hz']['p99_ms'])}",
                    _f(f["replay_angle_mae"], 4),
                    _f(f.get("angle_diff_vs_float32"), 4),
                ]
            )
    out = ["times in ms; MAE and |Δ| are angles in [-1, 1]", pt.get_string()]
    first = results["models"][0]["forms"][0]
    out.append(
        f"target: predict() within {results['target_overhead_pct']:g} % of session.run on the Donkeycar-shaped "
        f"model: {'met' if results['meets_target'] else 'MISSED'} ({first['predict_overhead_pct']:+.1f} %)"
    )
    out.append(f"machine: {results['machine']}")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (about 20 s)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    logging.disable(logging.INFO)  # the per-run profiler reports are not the figures
    results = measure(args.quick)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
