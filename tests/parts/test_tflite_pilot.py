"""TflitePilot and load_pilot: Donkeycar-style .tflite models (float32, uint8 and int8 full-integer) built once
with TensorFlow by examples/make_tflite_models.py and committed in tests/models/; here only LiteRT runs."""

import functools
import re
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.extras import install_command
from asyncdonkey.parts.pilot import OnnxPilot, PilotModelError, load_pilot
from asyncdonkey.parts.pilot_base import FrameEncoder
from asyncdonkey.parts.sim import Simulator
from asyncdonkey.parts.tflite_pilot import TflitePilot, tflite_interpreter
from asyncdonkey.pilot_export import SMALL_CONVS, SMALL_DENSE, export_donkey_linear_shaped

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "tests" / "models"
PIXELS = (7, 12345, 57599)  # examples/make_tflite_models.py PROBE_PIXELS: flat channels-last input indices


def frame(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (120, 160, 3), dtype=np.uint8)


def pixels(image: np.ndarray, layout: str = "NHWC") -> tuple[float, float]:
    """The first two probed input values, as the model received them (float32 frame / 255)."""
    x = image.astype(np.float32) / np.float32(255)
    flat = (x.transpose(2, 0, 1) if layout == "NCHW" else x).ravel()
    return float(flat[PIXELS[0]]), float(flat[PIXELS[1]])


@functools.cache
def _sim_frames(n: int) -> tuple[np.ndarray, ...]:
    sim = Simulator()
    out = []
    for k in range(n):
        sim.reset(s=7.0 * k + 1.0, offset=0.04 * (k - 3))
        out.append(sim.render())
    return tuple(out)


def sim_frames(n: int = 6) -> list[np.ndarray]:
    """Simulator frames from a few places on the track (rendered once per test run)."""
    return [f.copy() for f in _sim_frames(n)]


@pytest.fixture(scope="module")
def small_onnx(tmp_path_factory) -> OnnxPilot:
    """The same Donkeycar-style model and weights as tests/models/donkey_small*.tflite, exported to ONNX."""
    path = tmp_path_factory.mktemp("onnx") / "donkey_small.onnx"
    return OnnxPilot(export_donkey_linear_shaped(path, convs=SMALL_CONVS, dense=SMALL_DENSE), offload=False)


# ----------------------------------------------------------------------------------- Donkeycar's models
def test_donkeycar_float_model_loads_as_is_and_matches_onnx_of_the_same_weights(small_onnx):
    pilot = TflitePilot(MODELS / "donkey_small.tflite", offload=False)
    assert pilot.layout == "NHWC" and pilot.input_info.dtype == np.float32
    assert [o.name for o in pilot.output_info] == ["n_outputs0", "n_outputs1"]
    for image in sim_frames():
        np.testing.assert_allclose(pilot.predict(image), small_onnx.predict(image), atol=2e-6)


@pytest.mark.parametrize("kind", ["uint8", "int8"])
def test_full_integer_model_quantizes_the_frame_and_dequantizes_the_outputs(small_onnx, kind):
    pilot = TflitePilot(MODELS / f"donkey_small.{kind}.tflite", offload=False)
    info = pilot.input_info
    assert info.dtype == np.dtype(kind) and info.quantized and 0 < info.scale < 0.01
    assert pilot.encoder.mode == "table"  # calibrated on frames that never reach white: scale is not 1/255
    outs = pilot.output_info
    assert all(o.dtype == np.dtype(kind) and o.scale > 0 for o in outs)
    # the INT8 answer is the float answer to within some output quantization steps (of the 255 the calibrated
    # output range spans: 8 bits through five layers); a zero point read wrong would be 128 steps off
    steps = np.array([outs[0].scale, outs[1].scale])
    worst = 0.0
    for image in sim_frames():
        err = np.abs(np.array(pilot.predict(image)) - np.array(small_onnx.predict(image))) / steps
        worst = max(worst, float(err.max()))
    assert worst <= 20, f"INT8 output off by {worst:.1f} quantization steps"
    # and the answer is on the output grid: (q - zero point) * scale
    angle, _ = pilot.predict(sim_frames(1)[0])
    q = angle / outs[0].scale + outs[0].zero_point
    assert q == pytest.approx(round(q), abs=1e-6)


def test_uint8_and_int8_conversions_of_one_model_agree_exactly():
    """Same calibration, two interface types: the int8 frame is the uint8 one shifted by 128, so the
    answers must be identical (a wrong zero point or sign handling would show here)."""
    u = TflitePilot(MODELS / "donkey_small.uint8.tflite", offload=False)
    s = TflitePilot(MODELS / "donkey_small.int8.tflite", offload=False)
    for image in [*sim_frames(3), frame(1), frame(2)]:
        assert u.predict(image) == s.predict(image)


# ----------------------------------------------------------------------------------- preprocessing
@pytest.mark.parametrize(("model", "layout"), [("probe_pair", "NHWC"), ("probe_nchw", "NCHW")])
def test_frames_reach_the_model_scaled_by_1_over_255_in_its_layout(model, layout):
    pilot = TflitePilot(MODELS / f"{model}.tflite", offload=False)
    assert pilot.layout == layout
    for seed in range(3):
        image = frame(seed)
        assert pilot.predict(image) == pixels(image, layout)  # exact: float32 / 255, right pixels
    assert pilot.inferences == 3


def test_quantized_probe_returns_the_quantized_pixels():
    pilot = TflitePilot(MODELS / "probe_uint8.tflite", offload=False)
    info = pilot.input_info
    image = frame(3)
    flat = image.ravel()
    for got, idx in zip(pilot.predict(image), PIXELS[:2], strict=False):
        q = min(255, round(flat[idx] / 255 / info.scale) + info.zero_point)  # what the pilot must feed
        out = pilot.output_info[0]
        assert got == pytest.approx(min(1.0, (q - out.zero_point) * out.scale), abs=1e-9)


@pytest.mark.parametrize(
    ("dtype", "scale", "zero_point", "mode"),
    [
        (np.uint8, 1 / 255, 0, "copy"),
        (np.int8, 1 / 255, -128, "flip"),
        (np.uint8, 0.0036909, 0, "table"),
        (np.int8, 0.0036909, -128, "table"),
        (np.int8, 0.01, 3, "table"),
    ],
)
@pytest.mark.parametrize("layout", ["NHWC", "NCHW"])
def test_frame_encoder_quantizes_every_pixel_value_by_the_formula(dtype, scale, zero_point, mode, layout):
    enc = FrameEncoder(layout, dtype, np.float32(scale), zero_point)
    assert enc.mode == mode
    image = np.arange(120 * 160 * 3, dtype=np.int64).reshape(120, 160, 3).astype(np.uint8)  # every value, often
    out = np.empty((120, 160, 3) if layout == "NHWC" else (3, 120, 160), dtype)
    enc.encode(image, out)
    info = np.iinfo(dtype)
    real = image.astype(np.float64) / 255
    want = np.clip(np.round(real / float(np.float32(scale))) + zero_point, info.min, info.max).astype(dtype)
    np.testing.assert_array_equal(out, want if layout == "NHWC" else want.transpose(2, 0, 1))


# ----------------------------------------------------------------------------------- output forms
def test_two_outputs_are_read_in_the_signature_order_not_the_tensor_order():
    pilot = TflitePilot(MODELS / "probe_two.tflite", offload=False)
    image = frame(4)
    assert pilot.predict(image) == pixels(image)


def test_outputs_named_angle_and_throttle_are_matched_by_name():
    """probe_named returns throttle = pixel 1 and angle = pixel 0 and its interpreter lists the throttle first."""
    pilot = TflitePilot(MODELS / "probe_named.tflite", offload=False)
    assert pilot.interpreter.get_output_details()[0]["index"] != pilot._output_indices[0]
    image = frame(5)
    assert pilot.predict(image) == pixels(image)


def test_angle_only_model_takes_the_default_throttle():
    path = MODELS / "probe_angle.tflite"
    image = frame(6)
    assert TflitePilot(path, offload=False, default_throttle=0.35).predict(image) == (pixels(image)[0], 0.35)
    with pytest.raises(PilotModelError, match=r"probe_angle\.tflite outputs the angle only; pass default_throttle="):
        TflitePilot(path)


# ----------------------------------------------------------------------------------- load errors
def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(PilotModelError, match=r"TflitePilot\(nope\.tflite\): model file .*nope\.tflite does not exist"):
        TflitePilot(tmp_path / "nope.tflite")
    bad = tmp_path / "broken.tflite"
    bad.write_bytes(b"not a flatbuffer at all" * 20)
    with pytest.raises(PilotModelError, match=r"cannot load model .*broken\.tflite \(ValueError"):
        TflitePilot(bad)


def test_image_shape_mismatch_names_model_and_both_shapes():
    path = MODELS / "probe_66x200.tflite"
    with pytest.raises(PilotModelError) as info:
        TflitePilot(path)
    msg = str(info.value)
    assert "probe_66x200.tflite" in msg and "[?, 66, 200, 3]" in msg and "120x160x3" in msg
    pilot = TflitePilot(path, image_shape=(66, 200, 3), offload=False)
    image = np.random.default_rng(0).integers(0, 256, (66, 200, 3), dtype=np.uint8)
    assert pilot.predict(image) == tuple(
        (image.astype(np.float32).ravel()[list(PIXELS[:2])] / np.float32(255)).tolist()
    )


def test_two_inputs_and_three_values_are_refused():
    with pytest.raises(PilotModelError, match=r"probe_two_inputs\.tflite has 2 inputs .*a pilot takes one image"):
        TflitePilot(MODELS / "probe_two_inputs.tflite")
    with pytest.raises(
        PilotModelError, match=r"probe_three\.tflite outputs 'abc' float32 \[\?, 3\]; expected one output of 2 values"
    ):
        TflitePilot(MODELS / "probe_three.tflite", default_throttle=0.0)


def test_missing_runtime_says_what_to_install(monkeypatch):
    for module in ("ai_edge_litert.interpreter", "tflite_runtime.interpreter"):
        monkeypatch.setitem(sys.modules, module, None)  # as if not installed
    with pytest.raises(
        ImportError,
        match=r"running \.tflite pilots needs the tflite extra .*: " + re.escape(install_command("tflite")) + "$",
    ):
        tflite_interpreter()
    with pytest.raises(ImportError, match=re.escape(install_command("tflite"))):
        load_pilot(MODELS / "probe_pair.tflite")


def test_wrong_frames_name_the_part_and_the_shape():
    pilot = TflitePilot(MODELS / "probe_pair.tflite", name="pilot", offload=False)
    with pytest.raises(ValueError, match=r"pilot: cam/image_array frame is \(60, 80, 3\) uint8; expected"):
        pilot.predict(np.zeros((60, 80, 3), np.uint8))
    assert pilot.inferences == 0


# ----------------------------------------------------------------------------------- load_pilot
def test_load_pilot_picks_the_runtime_from_the_suffix(tmp_path):
    onnx_path = export_donkey_linear_shaped(tmp_path / "m.onnx", convs=SMALL_CONVS, dense=SMALL_DENSE)
    a = load_pilot(onnx_path, offload=False, threads=1)
    b = load_pilot(MODELS / "donkey_small.tflite", offload=False, threads=1)
    assert type(a) is OnnxPilot and a.intra_op_threads == 1
    assert type(b) is TflitePilot and b.num_threads == 1
    image = sim_frames(1)[0]
    np.testing.assert_allclose(a.predict(image), b.predict(image), atol=2e-6)
    for suffix, hint in ((".h5", "a Keras model: convert it"), (".pt", "expected one of .onnx, .tflite")):
        path = tmp_path / f"m{suffix}"
        path.write_bytes(b"x")
        with pytest.raises(PilotModelError, match=rf"m\{suffix}.*{hint}"):
            load_pilot(path)


def test_pilot_module_offers_tflite_pilot_lazily():
    from asyncdonkey.parts import pilot

    assert pilot.TflitePilot is TflitePilot


# ----------------------------------------------------------------------------------- in a Vehicle
class Frames:
    def __init__(self) -> None:
        self.frames = sim_frames(4)
        self.ticks = 0

    def run(self):
        self.ticks += 1
        return None if self.ticks == 1 else self.frames[self.ticks % len(self.frames)]


class Collect:
    def __init__(self) -> None:
        self.rows = []

    def run(self, image, angle, throttle):
        self.rows.append((image, angle, throttle))


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_int8_pilot_drives_a_vehicle_from_its_worker_thread():
    path = ROOT / "examples" / "models" / "sim_pilot.int8.tflite"
    pilot = load_pilot(path)
    reference = load_pilot(path, offload=False)
    assert pilot.encoder.mode == "flip"  # calibrated on [0, 1]: the int8 frame is the camera's bytes - 128
    threads = []
    original = pilot._infer
    pilot._infer = lambda image: (threads.append(threading.current_thread().name), original(image))[1]
    v = Vehicle()
    v.add(Frames(), outputs=["cam/image_array"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], name="pilot")
    out = Collect()
    v.add(out, inputs=["cam/image_array", "pilot/angle", "pilot/throttle"])
    report = await v.run(rate_hz=20, max_loop_count=8)
    assert report.loops == 8
    assert out.rows[0][1:] == (None, None)
    for image, angle, throttle in out.rows[1:]:
        assert (angle, throttle) == reference.predict(image)
    assert pilot.inferences == 7 and threads and all(t.startswith("tflite-pilot") for t in threads)
    assert pilot._executor is None  # shutdown() released the worker thread


def test_committed_simulator_tflite_pilot_matches_its_onnx_original():
    onnx_pilot = load_pilot(ROOT / "examples" / "models" / "sim_pilot.onnx", offload=False)
    tfl = load_pilot(ROOT / "examples" / "models" / "sim_pilot.tflite", offload=False)
    for image in sim_frames():
        np.testing.assert_allclose(tfl.predict(image), onnx_pilot.predict(image), atol=1e-5)


# ----------------------------------------------------------------------------------- replay
def test_replay_takes_a_tflite_pilot_and_scores_it_as_its_onnx_original(tmp_path):
    from asyncdonkey.commands.replay import ReplayError, replay
    from asyncdonkey.parts.tub import TubWriter

    tub = tmp_path / "tub"
    writer = TubWriter(
        tub, inputs=["cam/image_array", "user/angle", "user/throttle"], types=["image_array", "float", "float"]
    )
    for k, image in enumerate(sim_frames(12)):
        writer.run(image, 0.02 * k, 0.3)
    writer.shutdown()
    models = ROOT / "examples" / "models"
    a = replay(tub, models / "sim_pilot.onnx")
    b = replay(tub, models / "sim_pilot.tflite")
    assert a.records == b.records == 12
    assert b.pilot.endswith("sim_pilot.tflite")
    assert b.angle_mae == pytest.approx(a.angle_mae, abs=1e-5)
    assert b.throttle_mae == pytest.approx(a.throttle_mae, abs=1e-5)
    with pytest.raises(ReplayError, match=r"probe_66x200\.tflite wants input .*frames are 120x160x3"):
        replay(tub, MODELS / "probe_66x200.tflite")
