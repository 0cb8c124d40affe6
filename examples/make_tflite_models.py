"""Build the TFLite pilots the tests and the simulator use, with TensorFlow (run once, where TensorFlow installs).

    python3 -m venv /tmp/tfvenv
    /tmp/tfvenv/bin/pip install tensorflow-cpu tf-keras -e '.[tflite,test]'   # TensorFlow 2.21 on Python 3.11 here
    /tmp/tfvenv/bin/python examples/make_tflite_models.py              # writes the committed files below
    /tmp/tfvenv/bin/python examples/make_tflite_models.py --bench      # also benchmarks/models/ (not committed)

TensorFlow is far too heavy for the test environment, so the ``.tflite`` files are built here and committed, as
the ONNX models are; the tests need only LiteRT. Everything is deterministic in its inputs (seeded weights from
:func:`asyncdonkey.pilot_export.donkey_linear_weights`, simulator frames for calibration), so the tests can check
each file against a reference computed without TensorFlow.

What it writes:

``tests/models/donkey_small{,.uint8,.int8}.tflite``
    A Donkeycar ``KerasLinear``-style model (input ``img_in`` 120x160x3, four convolutions, a dense layer, heads
    ``n_outputs0`` = angle and ``n_outputs1`` = throttle) with the weights of
    ``donkey_linear_weights(0, SMALL_CONVS, SMALL_DENSE)``, built as a Keras model and converted as Donkeycar's
    ``keras_to_tflite`` does: float32 (no options), and full-integer quantization with a representative dataset
    of simulator frames, with uint8 input and outputs (Donkeycar's choice, for the Coral TPU) or int8 ones. The
    simulator's frames do not reach full white, so the input scale is not 1/255: the pilot's table path.
    ``export_donkey_linear_shaped(..., convs=SMALL_CONVS, dense=SMALL_DENSE)`` writes the same model as ONNX.
``tests/models/probe_*.tflite``
    Tiny models that output chosen input values (flat indices :data:`PROBE_PIXELS`), so a test sees exactly what
    the pilot fed the model: one ``[1, 2]`` output, two outputs, angle only, a quantized (uint8) probe, and models
    the pilot must refuse (three values, a 66x200 input, two inputs).
``examples/models/sim_pilot{,.int8}.tflite``
    The simulator's linear pilot (``examples/models/sim_pilot.onnx``: the same features and weights) in float32
    and in full-integer int8 (calibrated on the frames plus a black and a white one, so its input scale is
    1/255), for ``examples/car.py --pilot examples/models/sim_pilot.tflite``.
``benchmarks/models/donkey_linear{,.int8}.tflite`` (``--bench``)
    The full-size Donkeycar-shaped model of ``benchmarks/pilot.py`` (3.3 MB in float32, too big to commit).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
# Keras 2 (the tf-keras package), as Donkeycar 5 trains with: its conversion names the outputs after the layers
# (n_outputs0, n_outputs1), where Keras 3 would call them output_0, output_1.
os.environ.setdefault("TF_USE_LEGACY_KERAS", "1")

ROOT = Path(__file__).resolve().parents[1]
TEST_MODELS = ROOT / "tests" / "models"
SIM_MODELS = ROOT / "examples" / "models"
BENCH_MODELS = ROOT / "benchmarks" / "models"

#: Flat indices (channels-last) of the input values the probe models output.
PROBE_PIXELS = (7, 12345, 57599)
CALIBRATION_FRAMES = 64


def simulator_frames(n: int = CALIBRATION_FRAMES) -> np.ndarray:
    """``n`` simulator frames around the track (on and a little off the line), scaled to [0, 1] as pilots see them."""
    from asyncdonkey.parts.sim import Simulator

    sim = Simulator()
    rng = np.random.default_rng(0)
    frames = []
    for k in range(n):
        sim.reset(s=float(k) * 0.9, offset=float(rng.uniform(-0.25, 0.25)))
        frames.append(sim.render().astype(np.float32) / np.float32(255.0))
    return np.stack(frames)


def full_range(frames: np.ndarray) -> np.ndarray:
    """The frames plus a black and a white one: the calibrated input range is then exactly [0, 1], the input scale
    1/255, and the pilot feeds the camera's bytes to the model as they are (no per-pixel table)."""
    return np.concatenate([frames, np.zeros_like(frames[:1]), np.ones_like(frames[:1])])


def representative(frames: np.ndarray):
    def gen():
        for f in frames:
            yield [f[None]]

    return gen


def convert(tf, converter, frames: np.ndarray | None, io_type=None) -> bytes:
    """Donkeycar's ``keras_to_tflite``: plain float32, or (with calibration frames) full-integer quantization."""
    if frames is not None:
        converter.optimizations = [tf.lite.Optimize.DEFAULT]
        converter.representative_dataset = representative(frames)
        converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
        converter.inference_input_type = io_type
        converter.inference_output_type = io_type
    return converter.convert()


def lambda_model(keras, in_shape, outputs, inputs=("img_in",)):
    """A Keras model of one ``Lambda`` layer per output, each named after its output (the names the converted
    model's signature gives them): ``outputs`` maps a name to a function of the input(s)."""
    ins = [keras.Input(shape=in_shape, name=n, batch_size=None if len(inputs) == 1 else 1) for n in inputs]
    arg = ins[0] if len(ins) == 1 else ins
    outs = [keras.layers.Lambda(fn, name=name)(arg) for name, fn in outputs.items()]
    return keras.Model(inputs=ins, outputs=outs)


def write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    print(f"wrote {path.relative_to(ROOT)} ({len(data):,} bytes)")


def keras_linear(keras, convs, dense):
    """Donkeycar's ``KerasLinear`` layers (dropout left out: it does nothing at inference), named as Donkeycar names
    them, with the seeded weights every exporter shares."""
    from asyncdonkey.pilot_export import donkey_linear_weights

    weights = donkey_linear_weights(0, convs, dense)
    img_in = keras.Input(shape=(120, 160, 3), name="img_in")
    x = img_in
    for i, (w, b, stride) in enumerate(weights.convs):
        layer = keras.layers.Conv2D(w.shape[0], w.shape[2], strides=stride, activation="relu", name=f"conv2d_{i + 1}")
        x = layer(x)
        layer.set_weights([w.transpose(2, 3, 1, 0), b])
    x = keras.layers.Flatten(name="flattened")(x)
    for i, (w, b) in enumerate(weights.dense):
        layer = keras.layers.Dense(w.shape[1], activation="relu", name=f"dense_{i + 1}")
        x = layer(x)
        layer.set_weights([w, b])
    outputs = []
    for i, (w, b) in enumerate(weights.heads):
        layer = keras.layers.Dense(1, activation="linear", name=f"n_outputs{i}")
        outputs.append(layer(x))
        layer.set_weights([w, b])
    return keras.Model(inputs=[img_in], outputs=outputs, name="linear")


def keras_to_tflite(tf, model, frames=None, io_type=None) -> bytes:
    """As Donkeycar's ``keras_to_tflite`` converts a Keras pilot: ``TFLiteConverter.from_keras_model``."""
    return convert(tf, tf.lite.TFLiteConverter.from_keras_model(model), frames, io_type)


def probes(tf, keras, frames) -> dict[str, bytes]:
    i0, i1, i2 = PROBE_PIXELS

    def flat(x):
        return tf.reshape(x, [-1, int(np.prod(x.shape[1:]))])

    def pick(*idx):
        return lambda x: tf.gather(flat(x), list(idx), axis=1)

    def model(outputs, in_shape=(120, 160, 3), **kw):
        return lambda_model(keras, in_shape, outputs, **kw)

    pair = {"pair": pick(i0, i1)}
    out = {
        "probe_pair": keras_to_tflite(tf, model(pair)),
        "probe_two": keras_to_tflite(tf, model({"n_outputs0": pick(i0), "n_outputs1": pick(i1)})),
        "probe_named": keras_to_tflite(tf, model({"throttle": pick(i1), "angle": pick(i0)})),
        "probe_angle": keras_to_tflite(tf, model({"angle": pick(i0)})),
        "probe_three": keras_to_tflite(tf, model({"abc": pick(i0, i1, i2)})),
        "probe_66x200": keras_to_tflite(tf, model(pair, (66, 200, 3))),
        "probe_nchw": keras_to_tflite(tf, model(pair, (3, 120, 160))),
        "probe_uint8": keras_to_tflite(tf, model(pair), frames, tf.uint8),
        "probe_two_inputs": keras_to_tflite(
            tf, model({"pair": lambda ab: tf.concat([pick(i0)(ab[0]), pick(i1)(ab[1])], 1)}, inputs=("a", "b"))
        ),
    }
    return out


def sim_pilot(tf, keras, frames) -> dict[str, bytes]:
    """The simulator's linear pilot: the graph of ``export_linear_pilot`` in TensorFlow ops, weights read from
    the committed ONNX file."""
    import onnx
    from onnx import numpy_helper

    from asyncdonkey.pilot_export import CHANNEL_BIAS, CHANNEL_MIX, FEATURE_SIZE, POOL, TOP_ROW

    onnx_model = onnx.load(str(SIM_MODELS / "sim_pilot.onnx"))
    inits = {i.name: numpy_helper.to_array(i) for i in onnx_model.graph.initializer}
    W, b = inits["W"], inits["b"]

    def linear(img_in):
        crop = img_in[:, TOP_ROW:, :, :]
        maps = tf.nn.relu(tf.tensordot(crop, CHANNEL_MIX, axes=[[3], [0]]) + CHANNEL_BIAS)
        pooled = tf.nn.avg_pool2d(maps, POOL, POOL, "VALID")
        features = tf.reshape(tf.transpose(pooled, [0, 3, 1, 2]), [-1, FEATURE_SIZE])  # channel-major, as ONNX
        return tf.matmul(features, W) + b

    model = lambda_model(
        keras, (120, 160, 3), {"angle": lambda x: linear(x)[:, 0:1], "throttle": lambda x: linear(x)[:, 1:2]}
    )
    return {
        "sim_pilot": keras_to_tflite(tf, model),
        "sim_pilot.int8": keras_to_tflite(tf, model, full_range(frames), tf.int8),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bench", action="store_true", help="also the full-size benchmark models (not committed)")
    args = ap.parse_args(argv)
    try:
        import tensorflow as tf
        import tf_keras as keras
    except ImportError:
        print(
            "make_tflite_models.py: needs TensorFlow and tf-keras (pip install tensorflow-cpu tf-keras)",
            file=sys.stderr,
        )
        return 2
    from asyncdonkey.pilot_export import DONKEY_CONVS, DONKEY_DENSE, SMALL_CONVS, SMALL_DENSE

    tf.keras.utils.set_random_seed(0)
    frames = simulator_frames()
    small = keras_linear(keras, SMALL_CONVS, SMALL_DENSE)
    write(TEST_MODELS / "donkey_small.tflite", keras_to_tflite(tf, small))
    write(TEST_MODELS / "donkey_small.uint8.tflite", keras_to_tflite(tf, small, frames, tf.uint8))
    write(TEST_MODELS / "donkey_small.int8.tflite", keras_to_tflite(tf, small, frames, tf.int8))
    for name, data in probes(tf, keras, frames).items():
        write(TEST_MODELS / f"{name}.tflite", data)
    for name, data in sim_pilot(tf, keras, frames).items():
        write(SIM_MODELS / f"{name}.tflite", data)
    if args.bench:
        big = keras_linear(keras, DONKEY_CONVS, DONKEY_DENSE)
        write(BENCH_MODELS / "donkey_linear.tflite", keras_to_tflite(tf, big))
        write(BENCH_MODELS / "donkey_linear.int8.tflite", keras_to_tflite(tf, big, full_range(frames), tf.int8))
    return 0


if __name__ == "__main__":
    sys.exit(main())
