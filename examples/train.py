"""Train a pilot on the simulator in seconds (numpy only) and export it to ONNX.

    python examples/train.py --out models/sim_pilot.onnx
    python examples/train.py --tub data/tub --out models/pilot.onnx          # start from a recorded session

1. Collect: the scripted driver drives the simulated car headless (no event loop, as fast as the CPU allows);
   short steering pulses are added to what the car executes, not to the labels, so the data shows how to
   recover from mistakes. With ``--tub``, the recorded frames and user commands are the first data set
   instead.
2. Fit: ridge regression from small image features to the driver's angle and throttle; a DAgger-lite round
   lets the fitted pilot drive and the driver label what it sees, then refits.
3. Check: how closely the pilot imitates the driver on held-out driving (another place on the track, another
   driver seed), as the R² of its angle against always steering the mean angle, and a closed-loop drive: the
   pilot must complete laps without leaving the road. The drive is the test that counts: a pilot may steer
   its own way (a low or even negative R²) and still drive clean laps; its score is the share of the distance
   it drove before it first left the road.
4. Export: the features and the linear layer as one ONNX graph taking Donkeycar's input (a 120x160x3 image in
   [0, 1]), checked against numpy with onnxruntime.

See docs/simulator.md for the whole collect -> train -> drive -> replay loop.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from asyncdonkey.extras import MissingExtra, require
from asyncdonkey.parts.sim import ScriptedDriver, Simulator
from asyncdonkey.parts.sim.training import (
    LinearPilot,
    Perturbation,
    collect,
    drive,
    evaluate,
    samples_from_tub,
    train_pilot,
)


def features_and_exporter():
    """The one place the feature function and the ONNX exporter come from.

    ``linear_features(image)`` is the numpy twin of what the exported graph computes from the raw frame, so
    the pilot is trained on exactly what it will see at run time.
    """
    from asyncdonkey.pilot_export import export_linear_pilot, linear_features

    return linear_features, export_linear_pilot


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("models/sim_pilot.onnx"), help="ONNX file to write")
    ap.add_argument("--tub", type=Path, action="append", help="train first on this recorded tub (repeatable)")
    ap.add_argument("--frames", type=int, default=1500, help="frames collected with the scripted driver")
    ap.add_argument("--dagger", type=int, default=1, help="DAgger rounds (the pilot drives, the driver labels)")
    ap.add_argument("--dagger-frames", type=int, default=800, help="frames per DAgger round")
    ap.add_argument("--seed", type=int, default=0, help="seed of the scripted driver and its steering pulses")
    ap.add_argument("--check-seconds", type=float, default=60.0, help="closed-loop check drive (0: skip)")
    args = ap.parse_args(argv)

    try:  # before a minute of training, not at the export
        require("onnx", "quantize", "examples/train.py (it writes the pilot as an ONNX model)")
    except MissingExtra as exc:
        print(f"train.py: error: {exc}", file=sys.stderr)
        return 2
    try:
        features, export = features_and_exporter()
    except ImportError as exc:
        print(f"train.py: cannot import the ONNX exporter ({exc}); is asyncdonkey installed?", file=sys.stderr)
        return 2

    t0 = time.perf_counter()
    initial = None
    if args.tub:
        try:
            initial = samples_from_tub(args.tub, features=features)
        except (OSError, ValueError) as exc:
            print(f"train.py: {exc}", file=sys.stderr)
            return 2
        print(f"read {len(initial)} records from {', '.join(map(str, args.tub))}")
    pilot, report = train_pilot(
        features,
        frames=args.frames,
        dagger_rounds=args.dagger,
        dagger_frames=args.dagger_frames,
        seed=args.seed,
        initial=initial,
    )
    print(f"trained on {report.samples} frames in {time.perf_counter() - t0:.1f} s (ridge alpha {report.alpha})")

    # held out: another start on the track, another driver and pulse seed
    sim = Simulator(respawn_after_s=0.5)
    sim.reset(s=sim.track.length / 2)
    held = collect(
        sim,
        ScriptedDriver(sim.track, seed=args.seed + 1000),
        600,
        features=features,
        perturb=Perturbation(),
        seed=args.seed + 1001,
    )
    m = evaluate(pilot, held, report.baseline_angle)
    print(
        f"held-out imitation of the driver: angle R² {m['angle_r2']:.2f} (1: steers as the driver, 0: no "
        f"closer than always steering {report.baseline_angle:+.2f}); "
        f"angle MSE {m['angle_mse']:.4f} vs {m['baseline_angle_mse']:.4f}, MAE {m['angle_mae']:.3f}; "
        f"throttle MSE {m['throttle_mse']:.5f}"
    )

    if args.check_seconds > 0:
        sim = Simulator(respawn_after_s=0.5)
        result = drive(sim, pilot, args.check_seconds)
        print(
            f"closed loop, {result.seconds:.0f} s: {result.laps} laps, {result.distance:.1f} m, "
            f"clean {result.clean_fraction:.0%} (the share driven before first leaving the road); "
            f"|cte| mean {result.mean_abs_cte:.3f} m max {result.max_abs_cte:.3f} m, "
            f"off track {result.off_track_frames} frames"
        )
        if not result.clean or result.laps < 1:
            print("train.py: the pilot did not drive a clean lap; not exporting", file=sys.stderr)
            return 1

    args.out.parent.mkdir(parents=True, exist_ok=True)
    export(args.out, pilot.W, pilot.b)
    _check_onnx(args.out, pilot, sim.render())
    print(f"wrote {args.out}")
    return 0


def _check_onnx(path: Path, pilot: LinearPilot, image: np.ndarray) -> None:
    """The exported graph must compute what numpy trained: same outputs on a real frame."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = (image.astype(np.float32) / 255.0)[None]
    outs = sess.run(None, {sess.get_inputs()[0].name: x})
    got = np.concatenate([np.ravel(o) for o in outs])[:2]
    want = pilot.predict(pilot.features(image)[None])[0]
    if not np.allclose(got, want, atol=1e-4):
        raise SystemExit(f"train.py: ONNX output {got} differs from numpy {want}")


if __name__ == "__main__":
    sys.exit(main())
