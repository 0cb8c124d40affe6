"""`asyncdonkey quantize`: an INT8 QDQ copy of an ONNX pilot calibrated on a tub's simulator frames."""

import json
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey.commands.cli import main
from asyncdonkey.commands.quantize import QuantizeError, quantize_pilot, tub_frames
from asyncdonkey.parts.pilot import OnnxPilot
from asyncdonkey.parts.sim import ScriptedDriver, Simulator
from asyncdonkey.parts.tub import TubNotFoundError, TubWriter
from asyncdonkey.pilot_export import SMALL_CONVS, SMALL_DENSE, export_donkey_linear_shaped


def drive_frames(n: int, seed: int) -> list[np.ndarray]:
    sim = Simulator()
    driver = ScriptedDriver(sim.track, seed=seed)
    frames = []
    for _ in range(n):
        tel = sim.telemetry()
        frames.append(sim.render())
        angle, throttle = driver.run(tel.x, tel.y, tel.heading)
        for _ in range(4):  # 4 physics steps between frames: the camera sees the track go by
            sim.step(0.05, angle, throttle)
    return frames


@pytest.fixture(scope="module")
def tub(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("quantize") / "tub"
    writer = TubWriter(path, inputs=["cam/image_array", "user/angle"], types=["image_array", "float"], fsync=False)
    for image in drive_frames(60, seed=1):
        writer.run(image, 0.0)
    writer.shutdown()
    return path


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("quantize-model") / "donkey_small.onnx"
    return export_donkey_linear_shaped(path, convs=SMALL_CONVS, dense=SMALL_DENSE)


def test_int8_model_is_qdq_runs_in_onnx_pilot_and_stays_close_to_float(tub, model, tmp_path):
    import onnx

    out = tmp_path / "donkey_small.int8.onnx"
    report = quantize_pilot(model, tub, out, frames=40)
    assert report.frames == 40 and report.out == str(out) and report.per_channel
    graph = onnx.load(str(out)).graph
    ops = {n.op_type for n in graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "Conv"} <= ops
    int8_weights = [i for i in graph.initializer if i.data_type == onnx.TensorProto.INT8 and len(i.dims) == 4]
    assert len(int8_weights) == len(SMALL_CONVS)  # every convolution's weights are int8 now
    assert report.int8_bytes < report.float_bytes / 2.5
    # unchanged OnnxPilot, on frames it was not calibrated on: close to the float model, but not identical
    float_pilot, int8_pilot = OnnxPilot(model, offload=False), OnnxPilot(out, offload=False)
    diffs = [np.abs(np.subtract(int8_pilot.predict(f), float_pilot.predict(f))) for f in drive_frames(8, seed=7)]
    assert 0 < np.max(diffs) < 0.01
    assert report.angle_diff_max < 0.01 and report.float_ms > 0 and report.int8_ms > 0


def test_frames_are_spread_over_the_tub(tub):
    all_frames = tub_frames(tub, 1000)
    assert len(all_frames) == 60
    picked = tub_frames(tub, 4)
    assert [next(i for i, f in enumerate(all_frames) if np.array_equal(f, p)) for p in picked] == [0, 20, 39, 59]


def test_cli_writes_the_model_and_reports_json(tub, model, tmp_path, capsys):
    out = tmp_path / "q.onnx"
    assert main(["quantize", str(model), "--tub", str(tub), "--out", str(out), "--frames", "10", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 10 and report["out"] == str(out) and out.is_file()
    assert main(["quantize", str(model), "--tub", str(tub), "--out", str(out), "--frames", "10"]) == 0
    text = capsys.readouterr().out
    assert f"wrote {out}" in text and "INT8 vs float" in text and "warning" not in text


def test_default_output_is_beside_the_model(tub, model, tmp_path):
    copy = tmp_path / "mine.onnx"
    copy.write_bytes(model.read_bytes())
    report = quantize_pilot(copy, tub, frames=5)
    assert report.out == str(tmp_path / "mine.int8.onnx")


def test_errors_are_one_line_with_exit_2(tub, model, tmp_path, capsys):
    cases = [
        (["quantize", str(model), "--tub", str(tmp_path / "none")], "none"),
        (["quantize", str(tmp_path / "nope.onnx"), "--tub", str(tub)], "nope.onnx does not exist"),
        (["quantize", "tests/models/probe_pair.tflite", "--tub", str(tub)], "quantize takes an ONNX model"),
        (["quantize", str(model), "--tub", str(tub), "--out", str(tmp_path / "no" / "x.onnx")], "does not exist"),
        (["quantize", str(model), "--tub", str(tub), "--image-key", "cam/other"], "records no cam/other"),
    ]
    for argv, fragment in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("asyncdonkey quantize: error:") and fragment in err and "\n" not in err
    with pytest.raises(TubNotFoundError):
        quantize_pilot(model, tmp_path / "none", tmp_path / "x.onnx")
    with pytest.raises(QuantizeError, match="is the model itself"):
        quantize_pilot(model, tub, model)
