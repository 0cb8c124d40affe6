"""The ONNX exporter: the graph computes what numpy trains on, bytes are deterministic, onnxruntime loads it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pytest

from asyncdonkey.extras import install_command
from asyncdonkey.parts.sim import Simulator
from asyncdonkey.parts.sim.training import drive
from asyncdonkey.pilot_export import (
    FEATURE_SIZE,
    INPUT_NAME,
    export_donkey_linear_shaped,
    export_linear_pilot,
    linear_features,
)

if TYPE_CHECKING:
    import onnxruntime as ort

REPO = Path(__file__).resolve().parents[1]
SIM_PILOT = REPO / "examples" / "models" / "sim_pilot.onnx"


def sim_frames(n: int = 6) -> list[np.ndarray]:
    """Real simulator frames: on the centre line, off to each side, turned, and on a bend."""
    sim = Simulator()
    frames = []
    length = sim.track.length
    for k, (offset, heading) in enumerate([(0.0, 0.0), (0.15, 0.0), (-0.2, 0.1), (0.0, -0.3), (0.1, 0.2), (0, 0)]):
        sim.reset(s=length * k / n, offset=offset, heading_error=heading)
        frames.append(sim.render())
    return frames


def session(path: Path) -> ort.InferenceSession:
    import onnxruntime as ort

    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def feed(image: np.ndarray, layout: str) -> np.ndarray:
    x = (image.astype(np.float32) / np.float32(255))[None]
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2)) if layout == "NCHW" else x


def weights(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(0, 0.05, (FEATURE_SIZE, 2)).astype(np.float32), np.array([0.1, 0.3], np.float32)


@pytest.mark.parametrize("layout", ["NHWC", "NCHW"])
def test_graph_features_equal_numpy_features_on_simulator_frames(tmp_path, layout):
    """The whole feature vector, read from inside the graph, matches linear_features() to ~1e-5."""
    import onnx

    path = export_linear_pilot(tmp_path / "m.onnx", *weights(), layout=layout)
    model = onnx.load(str(path))
    model.graph.output.append(onnx.helper.make_tensor_value_info("features", onnx.TensorProto.FLOAT, [1, None]))
    probe = tmp_path / "probe.onnx"
    onnx.save(model, str(probe))
    sess = session(probe)
    for image in sim_frames():
        want = linear_features(image)
        got = sess.run(["features"], {INPUT_NAME: feed(image, layout)})[0].ravel()
        assert want.shape == got.shape == (FEATURE_SIZE,)
        np.testing.assert_allclose(got, want, atol=1e-5)
        assert np.count_nonzero(want) > FEATURE_SIZE // 4  # the thresholded maps are not all zero


@pytest.mark.parametrize("layout", ["NHWC", "NCHW"])
def test_graph_outputs_equal_features_times_weights(tmp_path, layout):
    W, b = weights(3)
    sess = session(export_linear_pilot(tmp_path / "m.onnx", W, b, layout=layout))
    assert [o.name for o in sess.get_outputs()] == ["angle", "throttle"]
    assert sess.get_inputs()[0].shape == ([1, 120, 160, 3] if layout == "NHWC" else [1, 3, 120, 160])
    for image in sim_frames(3):
        angle, throttle = sess.run(None, {INPUT_NAME: feed(image, layout)})
        assert angle.shape == throttle.shape == (1, 1)
        want = linear_features(image) @ W + b
        np.testing.assert_allclose([angle[0, 0], throttle[0, 0]], want, atol=1e-4)


def test_features_separate_lane_lines_from_asphalt_and_grass():
    """The white and yellow maps respond to where the lines are: shifting the car moves their mass."""
    sim = Simulator()
    centre_of_mass = []
    for offset in (-0.15, 0.15):
        sim.reset(s=1.0, offset=offset)
        maps = linear_features(sim.render()).reshape(4, 10, 20)
        yellow = maps[2]
        cols = np.arange(20)
        centre_of_mass.append(float((yellow.sum(axis=0) * cols).sum() / yellow.sum()))
    # the centre line appears on opposite sides of the image for the two offsets
    assert abs(centre_of_mass[0] - centre_of_mass[1]) > 2


def test_bytes_are_deterministic_and_depend_on_weights(tmp_path):
    W, b = weights(1)
    a = export_linear_pilot(tmp_path / "a.onnx", W, b).read_bytes()
    again = export_linear_pilot(tmp_path / "b.onnx", W.copy(), b.copy()).read_bytes()
    other = export_linear_pilot(tmp_path / "c.onnx", W, b + 1).read_bytes()
    assert a == again
    assert a != other
    d1 = export_donkey_linear_shaped(tmp_path / "d1.onnx", seed=5).read_bytes()
    d2 = export_donkey_linear_shaped(tmp_path / "d2.onnx", seed=5).read_bytes()
    d3 = export_donkey_linear_shaped(tmp_path / "d3.onnx", seed=6).read_bytes()
    assert d1 == d2 != d3


def test_ir_version_and_opset_are_readable_by_onnxruntime(tmp_path):
    import onnx

    for path in (
        export_linear_pilot(tmp_path / "l.onnx", *weights()),
        export_donkey_linear_shaped(tmp_path / "d.onnx"),
        SIM_PILOT,
    ):
        model = onnx.load(str(path))
        assert model.ir_version <= 13
        assert [(o.domain, o.version) for o in model.opset_import] == [("", 17)]
        onnx.checker.check_model(model)
        session(path)  # loads


def test_wrong_weight_shape_is_refused(tmp_path):
    with pytest.raises(ValueError, match=rf"W must be \({FEATURE_SIZE}, 2\).*got \(10, 2\)"):
        export_linear_pilot(tmp_path / "m.onnx", np.zeros((10, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="layout must be 'NHWC' or 'NCHW'"):
        export_linear_pilot(tmp_path / "m.onnx", *weights(), layout="HWC")


def test_linear_features_refuses_a_wrong_frame():
    with pytest.raises(ValueError, match=r"expected a \(120, 160, 3\) uint8 RGB frame, got shape \(60, 80, 3\)"):
        linear_features(np.zeros((60, 80, 3), np.uint8))


def test_donkey_shaped_model_has_two_one_value_outputs_in_both_layouts(tmp_path):
    import onnx

    nhwc = session(export_donkey_linear_shaped(tmp_path / "a.onnx", seed=0))
    nchw = session(export_donkey_linear_shaped(tmp_path / "b.onnx", seed=0, layout="NCHW"))
    assert [o.name for o in nhwc.get_outputs()] == ["n_outputs0", "n_outputs1"]
    conv_channels = [
        onnx.numpy_helper.to_array(t).shape[0]
        for t in onnx.load(str(tmp_path / "a.onnx")).graph.initializer
        if t.name.startswith("conv") and t.name.endswith("_w")
    ]
    assert conv_channels == [24, 32, 64, 64, 64]
    image = sim_frames(1)[0]
    a = nhwc.run(None, {INPUT_NAME: feed(image, "NHWC")})
    b = nchw.run(None, {INPUT_NAME: feed(image, "NCHW")})
    assert [o.shape for o in a] == [(1, 1), (1, 1)]
    np.testing.assert_allclose(np.ravel(a), np.ravel(b), rtol=1e-4, atol=1e-6)
    # the random weights still see the image: another frame gives other outputs
    c = nhwc.run(None, {INPUT_NAME: feed(np.full_like(image, 200), "NHWC")})
    assert not np.allclose(np.ravel(a), np.ravel(c))


@pytest.mark.subprocess
def test_importing_the_module_does_not_need_onnx(tmp_path):
    code = (
        "import sys; sys.modules['onnx'] = None\n"
        "import numpy as np\n"
        "from asyncdonkey.pilot_export import linear_features, export_linear_pilot, FEATURE_SIZE\n"
        "assert linear_features(np.zeros((120, 160, 3), np.uint8)).shape == (FEATURE_SIZE,)\n"
        "try:\n"
        f"    export_linear_pilot({str(tmp_path / 'x.onnx')!r}, np.zeros((FEATURE_SIZE, 2)), np.zeros(2))\n"
        "except ImportError as e:\n"
        "    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "needs the quantize extra" in out.stdout and install_command("quantize") in out.stdout


def test_committed_simulator_pilot_drives_a_clean_lap():
    """examples/models/sim_pilot.onnx, run through onnxruntime, keeps the simulated car on the road."""
    from asyncdonkey.parts.pilot import OnnxPilot

    pilot = OnnxPilot(SIM_PILOT, offload=False)
    result = drive(Simulator(respawn_after_s=0.5), pilot.predict, 32.0)
    assert result.laps >= 1
    assert result.clean
    assert result.max_abs_cte < 0.15
    assert pilot.inferences == 32 * 20
