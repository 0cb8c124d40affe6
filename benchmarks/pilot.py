"""Pilot inference cost: OnnxPilot's overhead over a bare ``session.run`` on the same model and session.

Two models: one with the layers of Donkeycar's ``KerasLinear`` (five convolutions, two dense layers, random
weights; about a millisecond of compute) and the simulator's linear pilot (``examples/models/sim_pilot.onnx``,
about a tenth of that). For each, per inference, median and p99 latency of:

* **session.run**: the floor, ``session.run`` on a frame already scaled to float32 (the pilot's own session,
  so thread settings are identical);
* **frame / 255 + session.run**: what any pilot taking uint8 frames must do at least (numpy's scaling into a
  new array, then ``session.run``);
* **predict()**: :meth:`OnnxPilot.predict` on the uint8 frame: checks, ``/ 255``, ``session.run``, unpacking,
  clipping; the overhead is ``predict / session.run - 1`` on medians (target <= 5 % for the Donkeycar-shaped
  model);
* **run() in a tick**: the pilot part's time in a Vehicle's profiler, ``run()`` awaited through the pilot's
  worker thread (offload on), the vehicle running flat out on uvloop, as ``Vehicle.start`` does. The extra
  over ``predict()`` is the hand-off to the worker thread and back to the event loop;
* **run() at 20 Hz**: the same at Donkeycar's drive rate, where every inference starts after 50 ms idle
  (caches and onnxruntime's threads cold, spinning off): what a car sees.

session.run, the scaled run and predict() alternate call by call, so drifts of the machine hit all alike.

    python benchmarks/pilot.py            # about 30 s
    python benchmarks/pilot.py --quick    # about 6 s
    python benchmarks/pilot.py --json     # figures as JSON
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking
from asyncdonkey.parts.pilot import OnnxPilot
from asyncdonkey.pilot_export import FEATURE_SIZE, export_donkey_linear_shaped, export_linear_pilot
from machine_info import describe

TARGET_OVERHEAD_PCT = 5.0
SIM_PILOT = Path(__file__).resolve().parents[1] / "examples" / "models" / "sim_pilot.onnx"


def camera_frame() -> np.ndarray:
    from asyncdonkey.parts.sim import Simulator

    return Simulator().render()


def _ms(samples: list[float] | np.ndarray) -> dict[str, float]:
    ms = np.asarray(samples) * 1e3
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)), "n": len(ms)}


def bare_and_predict(pilot: OnnxPilot, image: np.ndarray, calls: int) -> tuple[dict, dict, dict]:
    """Per call, in turn: bare ``session.run``, ``session.run`` on a freshly scaled frame, ``predict()``.

    Interleaving call by call (not in blocks) keeps a busy neighbour on a shared machine from landing on one
    path only."""
    sess, name = pilot.session, pilot.input_name
    x = pilot._preprocess(image).copy()
    perf = time.perf_counter
    bare = np.empty(calls)
    scaled = np.empty(calls)
    pred = np.empty(calls)
    for _ in range(20):  # warm all paths
        sess.run(None, {name: x})
        pilot.predict(image)
    for i in range(calls):
        a = perf()
        sess.run(None, {name: x})
        b = perf()
        sess.run(None, {name: (image.astype(np.float32) / np.float32(255.0))[None]})
        c = perf()
        pilot.predict(image)
        d = perf()
        bare[i], scaled[i], pred[i] = b - a, c - b, d - c
    return _ms(bare), _ms(scaled), _ms(pred)


class Camera:
    def __init__(self, image: np.ndarray) -> None:
        self.image = image

    def run(self) -> np.ndarray:
        return self.image


def in_tick(path: Path, image: np.ndarray, rate_hz: float, ticks: int) -> dict:
    """The pilot part's time per tick from the Vehicle's profiler (first and last samples dropped)."""
    pilot = OnnxPilot(path)
    v = Vehicle(profiler_window=ticks + 2)
    v.add(Camera(image), outputs=["cam/image_array"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], name="pilot")
    run_blocking(v.run(rate_hz, ticks))
    samples = v.profiler.series_for("pilot").recent()
    return _ms(samples)


def measure_model(label: str, path: Path, image: np.ndarray, quick: bool) -> dict:
    pilot = OnnxPilot(path, offload=False)
    bare, scaled, pred = bare_and_predict(pilot, image, 500 if quick else 4000)
    flat = in_tick(path, image, 1e6, 500 if quick else 4000)
    paced = in_tick(path, image, 20.0, 40 if quick else 300)
    return {
        "model": label,
        "file_bytes": path.stat().st_size,
        "threads": pilot.intra_op_threads,
        "session_run": bare,
        "session_run_with_scaling": scaled,
        "predict": pred,
        "run_in_tick": flat,
        "run_at_20hz": paced,
        "scaling_overhead_pct": (scaled["p50_ms"] / bare["p50_ms"] - 1) * 100,
        "predict_overhead_pct": (pred["p50_ms"] / bare["p50_ms"] - 1) * 100,
        "run_overhead_pct": (flat["p50_ms"] / bare["p50_ms"] - 1) * 100,
    }


def measure(quick: bool) -> dict:
    image = camera_frame()
    with tempfile.TemporaryDirectory(prefix="pilot-bench-") as tmp:
        donkey = export_donkey_linear_shaped(Path(tmp) / "donkey_linear.onnx")
        if SIM_PILOT.is_file():
            linear, linear_label = SIM_PILOT, "sim_pilot.onnx (linear)"
        else:
            rng = np.random.default_rng(0)
            w = rng.normal(0, 0.01, (FEATURE_SIZE, 2)).astype(np.float32)
            linear = export_linear_pilot(Path(tmp) / "linear.onnx", w, np.zeros(2, np.float32))
            linear_label = "linear (random weights)"
        models = [
            measure_model("Donkeycar-shaped CNN", donkey, image, quick),
            measure_model(linear_label, linear, image, quick),
        ]
    first = models[0]
    return {
        "machine": describe(),
        "quick": quick,
        "models": models,
        "target_overhead_pct": TARGET_OVERHEAD_PCT,
        "meets_target": first["predict_overhead_pct"] <= TARGET_OVERHEAD_PCT,
    }


def table(results: dict) -> str:
    pt = PrettyTable()
    pt.field_names = ["model", "path", "p50 (ms)", "p99 (ms)", "overhead vs session.run (p50)"]
    for m in results["models"]:
        rows = (
            ("session.run (floor)", m["session_run"], "-"),
            ("frame / 255 + session.run", m["session_run_with_scaling"], f"{m['scaling_overhead_pct']:+.1f} %"),
            ("predict()", m["predict"], f"{m['predict_overhead_pct']:+.1f} %"),
            ("run() in a tick, flat out", m["run_in_tick"], f"{m['run_overhead_pct']:+.1f} %"),
            ("run() in a tick, 20 Hz", m["run_at_20hz"], "-"),
        )
        for i, (path, r, over) in enumerate(rows):
            pt.add_row([m["model"] if i == 0 else "", path, f"{r['p50_ms']:.3f}", f"{r['p99_ms']:.3f}", over])
    out = [pt.get_string()]
    first = results["models"][0]
    out.append(
        f"target: predict() within {results['target_overhead_pct']:g} % of session.run on the Donkeycar-shaped "
        f"model: {'met' if results['meets_target'] else 'MISSED'} ({first['predict_overhead_pct']:+.1f} %)"
    )
    out.append(
        "run() adds the hand-off to the pilot's worker thread and back; at 20 Hz each inference starts cold "
        "after 50 ms idle"
    )
    out.append(f"intra-op threads {first['threads']}; machine: {results['machine']}")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples (about 6 s)")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    logging.disable(logging.INFO)  # the per-run profiler reports are not the figures
    results = measure(args.quick)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
