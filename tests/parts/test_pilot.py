"""OnnxPilot: load-time checks, Donkeycar preprocessing, output forms, errors, and the part in a Vehicle."""

import asyncio
import threading
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking
from asyncdonkey.parts.pilot import OnnxPilot, PilotModelError, physical_cores
from asyncdonkey.parts.sim import Simulator
from asyncdonkey.pilot_export import FEATURE_SIZE, export_donkey_linear_shaped, export_linear_pilot, linear_features

PIXELS = (7, 12345, 57599)  # flat indices into the model's input tensor
# onnx.TensorProto.FLOAT and .DOUBLE, named here so that collecting this file does not import onnx (1.2 s); the
# first test checks them against onnx's own
FLOAT, DOUBLE = 1, 11


def test_the_element_type_numbers_named_here_are_onnx_s_own() -> None:
    from onnx import TensorProto

    assert (FLOAT, DOUBLE) == (TensorProto.FLOAT, TensorProto.DOUBLE)


def save(path: Path, nodes, inits, in_shape, outputs, in_type: int = FLOAT) -> Path:
    """A small model written with onnx.helper, IR 8 / opset 17 (what onnxruntime reads)."""
    import onnx
    from onnx import TensorProto, helper

    g = helper.make_graph(
        nodes,
        "t",
        [helper.make_tensor_value_info("x", in_type, in_shape)],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, s) for n, s in outputs],
        initializer=inits,
    )
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    onnx.save(m, str(path))
    return path


def pixel_probe(path: Path, in_shape, outputs=(("pair", [1, 2]),)) -> Path:
    """Outputs two raw input values (flat indices PIXELS[0], PIXELS[1]) as one [1, 2] output, or as two
    [1, 1] outputs: what the pilot returns is then exactly what it fed the model."""
    from onnx import helper, numpy_helper

    inits = [
        numpy_helper.from_array(np.array([1, -1], np.int64), "flat"),
        numpy_helper.from_array(np.array(PIXELS[:2], np.int64), "idx"),
        numpy_helper.from_array(np.array([PIXELS[0]], np.int64), "i0"),
        numpy_helper.from_array(np.array([PIXELS[1]], np.int64), "i1"),
    ]
    nodes = [helper.make_node("Reshape", ["x", "flat"], ["f"])]
    if len(outputs) == 1 and outputs[0][1] == [1, 2]:
        nodes.append(helper.make_node("Gather", ["f", "idx"], [outputs[0][0]], axis=1))
    elif len(outputs) == 1:
        nodes.append(helper.make_node("Gather", ["f", "i0"], [outputs[0][0]], axis=1))
    else:
        nodes.append(helper.make_node("Gather", ["f", "i0"], [outputs[0][0]], axis=1))
        nodes.append(helper.make_node("Gather", ["f", "i1"], [outputs[1][0]], axis=1))
    return save(path, nodes, inits, in_shape, list(outputs))


def frame(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (120, 160, 3), dtype=np.uint8)


def expected_pixels(image: np.ndarray, layout: str) -> tuple[float, float]:
    x = image.astype(np.float32) / np.float32(255)
    flat = (x.transpose(2, 0, 1) if layout == "NCHW" else x).ravel()
    return float(flat[PIXELS[0]]), float(flat[PIXELS[1]])


# ------------------------------------------------------------------------------------- preprocessing
@pytest.mark.parametrize(
    ("layout", "shape"),
    [
        ("NHWC", [1, 120, 160, 3]),
        ("NCHW", [1, 3, 120, 160]),
        ("NHWC", ["batch", 120, 160, 3]),
        ("NCHW", [None, 3, 120, 160]),
    ],
)
def test_frames_reach_the_model_scaled_by_1_over_255_in_its_layout(tmp_path, layout, shape):
    pilot = OnnxPilot(pixel_probe(tmp_path / "p.onnx", shape), offload=False)
    assert pilot.layout == layout
    for seed in range(3):
        image = frame(seed)
        assert pilot.predict(image) == expected_pixels(image, layout)  # exact: float32 / 255, right pixels
    assert pilot.inferences == 3


def test_whole_frame_matches_numpy_through_the_linear_model(tmp_path):
    """A real exported pilot on real simulator frames: the part's answer is numpy's features @ W + b."""
    rng = np.random.default_rng(2)
    W = rng.normal(0, 0.02, (FEATURE_SIZE, 2)).astype(np.float32)
    b = np.array([0.05, 0.2], np.float32)
    for layout in ("NHWC", "NCHW"):
        pilot = OnnxPilot(export_linear_pilot(tmp_path / f"{layout}.onnx", W, b, layout=layout), offload=False)
        sim = Simulator()
        for s in (1.0, 9.0, 20.0):
            sim.reset(s=s, offset=0.1)
            image = sim.render()
            want = np.clip(linear_features(image) @ W + b, -1, 1)
            np.testing.assert_allclose(pilot.predict(image), want, atol=1e-5)


# ------------------------------------------------------------------------------------- output forms
def test_two_outputs_give_angle_then_throttle(tmp_path):
    path = pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3], (("n_outputs0", [1, 1]), ("n_outputs1", [1, 1])))
    image = frame(4)
    assert OnnxPilot(path, offload=False).predict(image) == expected_pixels(image, "NHWC")


def test_two_outputs_named_throttle_and_angle_are_matched_by_name(tmp_path):
    path = pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3], (("throttle", [1, 1]), ("angle", [1, 1])))
    image = frame(5)
    first, second = expected_pixels(image, "NHWC")
    assert OnnxPilot(path, offload=False).predict(image) == (second, first)


def test_angle_only_model_takes_the_default_throttle(tmp_path):
    path = pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3], (("angle", [1, 1]),))
    image = frame(6)
    pilot = OnnxPilot(path, offload=False, default_throttle=0.35)
    assert pilot.predict(image) == (expected_pixels(image, "NHWC")[0], 0.35)
    with pytest.raises(PilotModelError, match=r"p\.onnx outputs the angle only; pass default_throttle="):
        OnnxPilot(path)


def test_donkey_shaped_model_runs(tmp_path):
    pilot = OnnxPilot(export_donkey_linear_shaped(tmp_path / "d.onnx"), offload=False)
    angle, throttle = pilot.predict(Simulator().render())
    assert -1 <= angle <= 1 and -1 <= throttle <= 1
    assert pilot.last_inference_s > 0


def test_outputs_are_clipped_to_plus_minus_one(tmp_path):
    W = np.zeros((FEATURE_SIZE, 2), np.float32)
    pilot = OnnxPilot(export_linear_pilot(tmp_path / "m.onnx", W, np.array([3.0, -2.5], np.float32)), offload=False)
    assert pilot.predict(frame()) == (1.0, -1.0)


def test_nan_output_is_a_clear_error(tmp_path):
    from onnx import helper, numpy_helper

    nodes = [
        helper.make_node("ReduceMean", ["x"], ["m"], keepdims=0),
        helper.make_node("Add", ["m", "nan"], ["out"]),
    ]
    inits = [numpy_helper.from_array(np.array([[np.nan, 0.5]], np.float32), "nan")]
    pilot = OnnxPilot(save(tmp_path / "nan.onnx", nodes, inits, [1, 120, 160, 3], [("out", [1, 2])]), offload=False)
    with pytest.raises(ValueError, match=r"OnnxPilot\(nan\.onnx\): model .*nan\.onnx produced NaN"):
        pilot.predict(frame())


# ------------------------------------------------------------------------------------- load errors
def test_missing_file(tmp_path):
    with pytest.raises(PilotModelError, match=r"model file .*nope\.onnx does not exist"):
        OnnxPilot(tmp_path / "nope.onnx")


def test_corrupt_file(tmp_path):
    path = tmp_path / "broken.onnx"
    path.write_bytes(b"\x08\x07this is not a protobuf" * 10)
    with pytest.raises(PilotModelError, match=r"cannot load model .*broken\.onnx"):
        OnnxPilot(path)


def test_image_shape_mismatch_names_model_and_both_shapes(tmp_path):
    path = pixel_probe(tmp_path / "nvidia.onnx", [1, 66, 200, 3])
    with pytest.raises(PilotModelError) as info:
        OnnxPilot(path)
    msg = str(info.value)
    assert "nvidia.onnx" in msg and "[1, 66, 200, 3]" in msg and "120x160x3" in msg
    # with the matching image_shape it loads
    assert OnnxPilot(path, image_shape=(66, 200, 3), offload=False).layout == "NHWC"


@pytest.mark.parametrize(
    ("in_shape", "in_type", "match"),
    [
        ([1, 160, 120, 3], FLOAT, r"wants input 'x' \[1, 160, 120, 3\]"),
        ([1, 120, 160, 4], FLOAT, r"wants input 'x' \[1, 120, 160, 4\]"),
        ([4, 120, 160, 3], FLOAT, "has batch 4; expected 1 or dynamic"),
        ([120, 160, 3], FLOAT, r"expected a 4-D float tensor"),
        ([1, 120, 160, 3], DOUBLE, r"tensor\(double\).*expected a 4-D float tensor"),
    ],
)
def test_unusable_inputs_are_refused(tmp_path, in_shape, in_type, match):
    from onnx import helper

    nodes = [helper.make_node("ReduceMean", ["x"], ["m"], keepdims=0), helper.make_node("Cast", ["m"], ["out"], to=1)]
    path = save(tmp_path / "bad_in.onnx", nodes, [], in_shape, [("out", [])], in_type=in_type)
    with pytest.raises(PilotModelError, match=match) as info:
        OnnxPilot(path)
    assert "bad_in.onnx" in str(info.value)


@pytest.mark.parametrize(
    "outputs",
    [
        (("a", [1, 3]),),
        (("a", [1, 1]), ("b", [1, 2])),
        (("a", [1, 1]), ("b", [1, 1]), ("c", [1, 1])),
    ],
)
def test_unusable_outputs_are_refused(tmp_path, outputs):
    from onnx import helper, numpy_helper

    nodes = [helper.make_node("ReduceMean", ["x"], ["m"], keepdims=0)]
    inits = []
    for name, shape in outputs:
        inits.append(numpy_helper.from_array(np.zeros(shape, np.float32), f"{name}_zero"))
        nodes.append(helper.make_node("Add", ["m", f"{name}_zero"], [name]))
    path = save(tmp_path / "bad_out.onnx", nodes, inits, [1, 120, 160, 3], list(outputs))
    with pytest.raises(PilotModelError, match=r"bad_out\.onnx outputs .*expected one output of 2 values"):
        OnnxPilot(path, default_throttle=0.0)


def test_undeclared_output_size_is_checked_by_the_warm_up_run(tmp_path):
    """An output whose size depends on the data is run once at load: 3 values is refused there, not on the
    first tick (and 2 values is accepted as angle, throttle)."""
    from onnx import TensorProto, helper, numpy_helper

    def model(n: float) -> Path:
        nodes = [
            helper.make_node("Reshape", ["x", "flat"], ["f"]),
            helper.make_node("ReduceMax", ["x"], ["mx"], keepdims=0),
            helper.make_node("Mul", ["mx", "zero"], ["z"]),
            helper.make_node("Add", ["z", "n"], ["nf"]),
            helper.make_node("Cast", ["nf"], ["end"], to=TensorProto.INT64),
            helper.make_node("Slice", ["f", "start", "end", "axis"], ["out"]),
        ]
        inits = [
            numpy_helper.from_array(np.array([1, -1], np.int64), "flat"),
            numpy_helper.from_array(np.array([0.0], np.float32), "zero"),
            numpy_helper.from_array(np.array([n], np.float32), "n"),
            numpy_helper.from_array(np.array([0], np.int64), "start"),
            numpy_helper.from_array(np.array([1], np.int64), "axis"),
        ]
        return save(tmp_path / f"dyn{int(n)}.onnx", nodes, inits, [1, 120, 160, 3], [("out", None)])

    with pytest.raises(PilotModelError, match=r"dyn3\.onnx produced outputs of \[3\] values"):
        OnnxPilot(model(3.0), default_throttle=0.0)
    image = frame(11)
    first = image.astype(np.float32).ravel()[:2] / np.float32(255)
    assert OnnxPilot(model(2.0), offload=False).predict(image) == tuple(first.tolist())


# ------------------------------------------------------------------------------------- frames
def test_wrong_frames_name_the_part_and_the_shape(tmp_path):
    pilot = OnnxPilot(pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3]), name="pilot", offload=False)
    with pytest.raises(
        ValueError, match=r"pilot: cam/image_array frame is \(60, 80, 3\) uint8; expected \(120, 160, 3\)"
    ):
        pilot.predict(np.zeros((60, 80, 3), np.uint8))
    with pytest.raises(ValueError, match=r"pilot: cam/image_array frame is \(120, 160, 3\) float32"):
        pilot.predict(np.zeros((120, 160, 3), np.float32))
    with pytest.raises(ValueError, match=r"frame is a list"):
        pilot.predict([[0, 0, 0]])
    assert pilot.inferences == 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_run_before_the_first_frame_returns_none_none(tmp_path):
    pilot = OnnxPilot(pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3]))
    assert await pilot.run(None) == (None, None)
    assert pilot.inferences == 0
    image = frame(9)
    assert await pilot.run(image) == expected_pixels(image, "NHWC")
    pilot.shutdown()
    with pytest.raises(RuntimeError, match="after shutdown"):
        await pilot.run(image)


def test_session_settings(tmp_path):
    pilot = OnnxPilot(pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3]), intra_op_threads=1)
    assert pilot.intra_op_threads == 1
    assert pilot.session.get_providers() == ["CPUExecutionProvider"]
    assert OnnxPilot(tmp_path / "p.onnx").intra_op_threads == physical_cores() >= 1
    with pytest.raises(ValueError, match="intra_op_threads must be a positive int"):
        OnnxPilot(tmp_path / "p.onnx", intra_op_threads=0)


# ------------------------------------------------------------------------------------- in a Vehicle
class SimFrames:
    """A camera part serving real simulator frames from a few poses; None on the first tick (warm-up)."""

    def __init__(self) -> None:
        sim = Simulator()
        self.frames = []
        for k in range(5):
            sim.reset(s=3.0 * k, offset=0.05 * (k - 2))
            self.frames.append(sim.render())
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
async def test_pilot_outputs_land_in_memory_under_its_run_condition():
    path = Path(__file__).resolve().parents[2] / "examples" / "models" / "sim_pilot.onnx"
    pilot = OnnxPilot(path)
    reference = OnnxPilot(path, offload=False)
    cam = SimFrames()
    v = Vehicle()
    v.mem["run_pilot"] = False
    v.add(cam, outputs=["cam/image_array"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="run_pilot")
    out = Collect()
    v.add(out, inputs=["cam/image_array", "pilot/angle", "pilot/throttle"])

    class Switch:
        def run(self):
            return len(out.rows) >= 3  # the pilot is switched on from the fourth tick

    v.add(Switch(), outputs=["run_pilot"])
    report = await v.run(rate_hz=20, max_loop_count=12)
    assert report.loops == 12 and report.overruns == 0  # executor work takes no virtual time
    assert [r[1] for r in out.rows[:3]] == [None] * 3
    for image, angle, throttle in out.rows[3:]:
        assert (angle, throttle) == reference.predict(image)
        assert -0.5 < angle < 0.5 and 0 < throttle <= 1
    assert pilot.inferences == 9
    assert pilot._executor is None  # shutdown() released the worker thread


class GatedPilot(OnnxPilot):
    """The real pilot, with inference held until a concurrently running asyncio task has answered.

    ``predict`` wakes the task through the loop (``call_soon_threadsafe``, as an I/O event would) and waits
    for it to open a gate. If ``run()`` computed on the event-loop thread, the task could never run while
    inference waits, and the wait would time out."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.gate = threading.Event()
        self.wake = asyncio.Event()
        self.loop = asyncio.get_running_loop()
        self.threads: list[str] = []
        self.answered: list[bool] = []

    def predict(self, image):
        self.threads.append(threading.current_thread().name)
        self.loop.call_soon_threadsafe(self.wake.set)
        self.answered.append(self.gate.wait(timeout=5.0))
        self.gate.clear()
        return super().predict(image)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_other_tasks_run_while_inference_is_in_the_executor(tmp_path):
    pilot = GatedPilot(export_donkey_linear_shaped(tmp_path / "d.onnx"))
    served = 0

    async def other_task():  # e.g. a serial reader or a web client being served during inference
        nonlocal served
        while True:
            await pilot.wake.wait()
            pilot.wake.clear()
            served += 1
            pilot.gate.set()  # predict() is still waiting in its thread for this

    task = asyncio.create_task(other_task())
    v = Vehicle()
    v.add(SimFrames(), outputs=["cam/image_array"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], name="pilot")
    try:
        report = await v.run(rate_hz=20, max_loop_count=6)
    finally:
        task.cancel()
    assert report.loops == 6
    assert pilot.answered == [True] * 5 and served == 5
    assert all(name.startswith("onnx-pilot") for name in pilot.threads)
    assert pilot.inferences == 5 and v.mem["pilot/angle"] is not None


@pytest.mark.realtime
def test_offload_false_computes_on_the_loop_thread(tmp_path):
    pilot = OnnxPilot(pixel_probe(tmp_path / "p.onnx", [1, 120, 160, 3]), offload=False)
    seen = []
    original = pilot.predict

    async def main():
        pilot.predict = lambda image: (seen.append(threading.current_thread()), original(image))[1]
        return await pilot.run(frame())

    assert run_blocking(main(), use_uvloop=False) == expected_pixels(frame(), "NHWC")
    assert seen == [threading.main_thread()]


@pytest.mark.realtime
def test_profiler_shows_the_pilot_time_on_a_real_loop(tmp_path):
    """On real time the profiler row for the pilot holds the inference (at least the compute it measured)."""
    pilot = OnnxPilot(export_donkey_linear_shaped(tmp_path / "d.onnx"))
    v = Vehicle()
    v.add(SimFrames(), outputs=["cam/image_array"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], name="pilot")
    report = run_blocking(v.run(rate_hz=50, max_loop_count=12), use_uvloop=False)
    row = report.parts["pilot"]
    assert row is not None
    assert pilot.inferences == 11
    # every tick in the window (the first and last are dropped) awaited a full inference of this CNN,
    # which takes well over 0.1 ms on any CPU
    assert row["min"] > 0.1
    assert "pilot" in v.profiler.table()
