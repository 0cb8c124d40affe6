"""Write an ONNX model shaped like Donkeycar's linear pilot, to try the pilot part before training one.

    python examples/make_model.py                       # models/donkey_linear.onnx
    python examples/make_model.py --out /tmp/m.onnx --layout NCHW

The layers are those of Donkeycar's ``KerasLinear`` (five convolutions, two dense layers, angle and throttle
heads) with seeded random weights: the compute is realistic, the steering is not. The file is the same
byte for byte on every run with the same arguments. Then it loads the model the way the car does
(:class:`asyncdonkey.parts.pilot.OnnxPilot`) and prints its shapes and what one inference costs here.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("models/donkey_linear.onnx"), help="ONNX file to write")
    ap.add_argument("--seed", type=int, default=0, help="weight seed")
    ap.add_argument("--layout", choices=["NHWC", "NCHW"], default="NHWC", help="input layout (Donkeycar: NHWC)")
    args = ap.parse_args(argv)
    try:
        from asyncdonkey.parts.pilot import OnnxPilot
        from asyncdonkey.pilot_export import export_donkey_linear_shaped
    except ImportError as exc:
        print(f"make_model.py: {exc}", file=sys.stderr)
        return 2

    args.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        path = export_donkey_linear_shaped(args.out, seed=args.seed, layout=args.layout)
    except ImportError as exc:
        print(f"make_model.py: {exc}", file=sys.stderr)
        return 2
    data = path.read_bytes()
    print(f"wrote {path} ({len(data):,} bytes, sha256 {hashlib.sha256(data).hexdigest()[:16]})")

    pilot = OnnxPilot(path, offload=False)
    inp = pilot.session.get_inputs()[0]
    print(f"input  {inp.name} {inp.shape} float32 in [0, 1] ({pilot.layout})")
    for o in pilot.session.get_outputs():
        print(f"output {o.name} {o.shape}")
    image = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    times = []
    for _ in range(50):
        t = time.perf_counter()
        angle, throttle = pilot.predict(image)
        times.append(time.perf_counter() - t)
    print(
        f"inference: median {np.median(times) * 1e3:.2f} ms over {len(times)} runs "
        f"({pilot.intra_op_threads} intra-op threads); sample output angle {angle:+.4f} throttle {throttle:+.4f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
