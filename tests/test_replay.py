"""`asyncdonkey replay`: scores against numpy, records reach the pilot at their recorded times, skips are counted,
CSV rows are exact and identical run to run, the CLI's errors are one line with exit 2, and ten minutes of
driving replay in seconds.

Tubs are recorded by a Vehicle on the virtual clock through the real TubWriter; the ONNX test model's angle is
the red channel's mean mapped to [-1, 1] and its throttle the green channel's mean in [0, 1], so the expected
pilot output of every recorded frame is a numpy one-liner over the decoded image.
"""

from __future__ import annotations

import asyncio
import csv
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey import Vehicle, get_clock
from asyncdonkey.commands.replay import CSV_COLUMNS, ReplayError, replay
from asyncdonkey.parts.tub import Tub, TubNotFoundError, TubWriter
from asyncdonkey.testing import VirtualClockLoop

CLI = [sys.executable, "-m", "asyncdonkey.commands"]
INPUTS = ["cam/image_array", "user/angle", "user/throttle"]
TYPES = ["image_array", "float", "float"]
#: the model sums 19,200 pixels in float32; numpy checks in float64 (differences seen: about 1e-5)
TOL = 1e-4


# ------------------------------------------------------------------------------------------------ helpers
def write_model(path: Path, rows: int = 120, cols: int = 160) -> Path:
    """angle = 2 * mean(R) - 1, throttle = mean(G), on the frame scaled to [0, 1] (what OnnxPilot feeds)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    inits = [
        numpy_helper.from_array(np.array([0], np.int64), "c0"),
        numpy_helper.from_array(np.array([1], np.int64), "c1"),
        numpy_helper.from_array(np.array([2], np.int64), "c2"),
        numpy_helper.from_array(np.array([3], np.int64), "axis"),
        numpy_helper.from_array(np.array([1, 1], np.int64), "shape11"),
        numpy_helper.from_array(np.array(2.0, np.float32), "two"),
        numpy_helper.from_array(np.array(1.0, np.float32), "one"),
    ]
    nodes = [
        helper.make_node("Slice", ["img_in", "c0", "c1", "axis"], ["red"]),
        helper.make_node("Slice", ["img_in", "c1", "c2", "axis"], ["green"]),
        helper.make_node("ReduceMean", ["red"], ["red_mean"], axes=[1, 2, 3], keepdims=1),
        helper.make_node("ReduceMean", ["green"], ["green_mean"], axes=[1, 2, 3], keepdims=1),
        helper.make_node("Mul", ["red_mean", "two"], ["red2"]),
        helper.make_node("Sub", ["red2", "one"], ["angle4"]),
        helper.make_node("Reshape", ["angle4", "shape11"], ["angle"]),
        helper.make_node("Reshape", ["green_mean", "shape11"], ["throttle"]),
    ]
    graph = helper.make_graph(
        nodes,
        "red_green_pilot",
        [helper.make_tensor_value_info("img_in", TensorProto.FLOAT, [1, rows, cols, 3])],
        [
            helper.make_tensor_value_info("angle", TensorProto.FLOAT, [1, 1]),
            helper.make_tensor_value_info("throttle", TensorProto.FLOAT, [1, 1]),
        ],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 10
    onnx.checker.check_model(model)
    path.write_bytes(model.SerializeToString())
    return path


def expected_outputs(image: np.ndarray) -> tuple[float, float]:
    x = image.astype(np.float64) / 255.0
    return 2.0 * x[..., 0].mean() - 1.0, x[..., 1].mean()


class Drive:
    """A recorded session: frames whose red and green levels change every tick, a wavy user angle, a steady
    throttle, and pauses in the recording (ticks 30-35 of every 40 are not recorded) so the recorded times
    have irregular gaps. ``holes`` maps a tick to the channel left out of its record."""

    def __init__(self, rows: int, cols: int, holes: dict[int, str] | None = None) -> None:
        self.rows, self.cols, self.holes, self.k = rows, cols, holes or {}, 0
        yy, xx = np.mgrid[0:rows, 0:cols]
        self.texture = ((xx * 3 + yy * 2) % 40).astype(np.int16)

    def run(self):
        k = self.k = self.k + 1
        img = np.empty((self.rows, self.cols, 3), np.uint8)
        img[..., 0] = np.clip(self.texture + (k * 37) % 200, 0, 255)
        img[..., 1] = np.clip(self.texture + (k * 11) % 180 + 20, 0, 255)
        img[..., 2] = 90
        values = [img, float(np.sin(k / 9.0)), 0.35 + 0.1 * np.cos(k / 17.0)]
        hole = self.holes.get(k)
        if hole is not None:
            values[INPUTS.index(hole)] = None
        return (*values, k % 40 < 30)


def record_tub(path: Path, ticks: int, rows: int = 120, cols: int = 160, holes=None) -> Path:
    """Record ``ticks`` ticks at 20 Hz on the virtual clock through TubWriter (its timestamps follow the
    virtual clock)."""

    async def drive() -> None:
        v = Vehicle()
        v.add(Drive(rows, cols, holes), outputs=[*INPUTS, "recording"])
        w = TubWriter(path, INPUTS, TYPES, queue_size=ticks + 1, fsync=False)
        v.add(w, inputs=INPUTS, run_condition="recording", shutdown_timeout=120)
        await v.run(rate_hz=20, max_loop_count=ticks)
        assert w.stats.dropped == 0 and w.stats.written == w.stats.accepted

    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        runner.run(drive())
    return path


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    return record_tub(tmp_path_factory.mktemp("replay") / "tub", ticks=160)


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return write_model(tmp_path_factory.mktemp("models") / "red_green.onnx")


def run_cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, "replay", *map(str, args)], capture_output=True, text=True, timeout=timeout)


def assert_one_line_error(proc: subprocess.CompletedProcess[str], *fragments: str) -> None:
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for f in fragments:
        assert f in lines[0], lines[0]


# --------------------------------------------------------------------------------------------- scoring
def test_errors_match_numpy_over_the_same_records(recorded, model):
    report = replay(recorded, model)
    recs = list(Tub(recorded))
    assert len(recs) == 120  # 160 ticks, 30 of every 40 recorded
    expected = np.array([expected_outputs(r["cam/image_array"]) for r in recs])
    user = np.array([(r["user/angle"], r["user/throttle"]) for r in recs])

    assert report.records == 120 and report.skipped == {}
    assert [row.index for row in report.rows] == [r["_index"] for r in recs]
    pilot = np.array([(row.pilot_angle, row.pilot_throttle) for row in report.rows])
    np.testing.assert_allclose(pilot, expected, atol=TOL)
    err = np.abs(expected - user)
    assert report.angle_mae == pytest.approx(err[:, 0].mean(), abs=TOL)
    assert report.throttle_mae == pytest.approx(err[:, 1].mean(), abs=TOL)
    assert report.angle_max_err == pytest.approx(err[:, 0].max(), abs=TOL)
    assert report.throttle_max_err == pytest.approx(err[:, 1].max(), abs=TOL)
    assert report.baseline_angle_mae == pytest.approx(np.abs(user[:, 0]).mean(), abs=1e-12)
    assert set(report.inference_ms) == {"avg", "50%", "90%", "99%", "max"}
    assert 0 < report.inference_ms["50%"] <= report.inference_ms["max"]


def test_records_reach_the_pilot_at_their_recorded_times(recorded):
    seen: list[float] = []

    class ClockReadingPilot:
        """Reads the runtime clock when each frame arrives (predict runs on the replay's loop thread)."""

        def predict(self, image):
            seen.append(get_clock().now())
            return 0.0, 0.0

    report = replay(recorded, ClockReadingPilot())
    stamps = np.array([r["_timestamp_ms"] for r in Tub(recorded)], dtype=np.float64)
    offsets = (stamps - stamps[0]) / 1000.0
    gaps = np.diff(stamps)
    assert gaps.min() < 60 and gaps.max() > 500  # 50 ms ticks and the recording pauses: irregular on purpose
    arrivals = np.array(seen) - seen[0]
    np.testing.assert_allclose(arrivals, offsets, rtol=0, atol=1e-9)
    np.testing.assert_allclose([row.at_s for row in report.rows], offsets, rtol=0, atol=1e-9)
    assert report.replayed_s == pytest.approx(offsets[-1], abs=1e-9)
    assert report.late_ms_max == 0.0


@pytest.mark.realtime
def test_real_time_speed_keeps_the_recorded_pace(tmp_path):
    tub = record_tub(tmp_path / "tub", ticks=29)  # 28 gaps of 50 ms: 1.4 s recorded
    fds = set(os.listdir("/proc/self/fd"))
    report = replay(tub, lambda image: (0.0, 0.0), speed=10.0)
    assert set(os.listdir("/proc/self/fd")) <= fds  # the player's timer (one for every tick) is released
    offsets = np.array([row.at_s for row in report.rows])
    stamps = np.array([r["_timestamp_ms"] for r in Tub(tub)], dtype=np.float64)
    due = (stamps - stamps[0]) / 1000.0 / 10.0
    assert report.records == 29 and report.speed == 10.0
    assert np.all(offsets >= due - 1e-9)  # never early on a real clock
    assert report.real_s >= due[-1]
    assert report.late_ms_max >= 0.0
    # the summary tells the truth: 1.4 s of recording, at (at most) ten times its pace, not "0.14 s ... (1x)"
    assert report.replayed_s == pytest.approx(1.4, abs=1e-9)
    pace = report.replayed_s / report.real_s
    assert pace <= 10.0
    shown = re.search(r"replayed +1\.4 s of recording in [\d.]+ s \(([\d.]+)x\), real time x10", report.format_table())
    assert shown is not None, report.format_table()
    assert float(shown.group(1)) == pytest.approx(pace, rel=0.05)


# ----------------------------------------------------------------------------------------------- skips
def test_deleted_and_unplayable_records_are_skipped_and_counted(tmp_path, model):
    # ticks 1-based; records are made at ticks 1-29, so record index = tick - 1
    holes = {3: "cam/image_array", 5: "user/angle", 6: "user/throttle", 8: "user/angle"}
    path = record_tub(tmp_path / "tub", ticks=28, holes=holes)
    tub = Tub(path)
    tub.delete_records([10, 11, 12])
    (path / "images" / "20_cam_image_array_.jpg").unlink()  # a lost image file
    (path / "images" / "21_cam_image_array_.jpg").write_bytes(b"")  # a truncated one
    report = replay(path, model)
    assert report.skipped == {"bad_image": 2, "no_image": 1, "no_user_values": 3}
    played = [row.index for row in report.rows]
    assert played == [i for i in range(28) if i not in {2, 4, 5, 7, 10, 11, 12, 20, 21}]
    assert report.records == 19
    kept = [r for r in Tub(path) if r["_index"] in set(played)]
    exp = np.array([expected_outputs(r["cam/image_array"])[0] for r in kept])
    assert report.angle_mae == pytest.approx(np.abs(exp - [r["user/angle"] for r in kept]).mean(), abs=TOL)


def test_corrupt_catalog_lines_are_reported_with_where_they_are(tmp_path, model):
    path = record_tub(tmp_path / "tub", ticks=12)
    catalog = path / "catalog_0.catalog"
    lines = catalog.read_bytes().split(b"\n")
    lines[3] = b"\x00" * len(lines[3])  # a power cut's zeros: found when the tub is opened
    lines[7] = b"{" + b"x" * (len(lines[7]) - 2) + b"}"  # looks like a record, is not JSON: found when read
    catalog.write_bytes(b"\n".join(lines))
    report = replay(path, model, csv_path=tmp_path / "rows.csv")
    assert report.records == 10 and report.skipped == {"corrupt": 2}
    assert report.corrupt == [
        {"index": 3, "catalog": "catalog_0.catalog", "line": 4},
        {"index": 7, "catalog": "catalog_0.catalog", "line": 8},
    ]
    table = report.format_table()
    assert "10 scored, 2 skipped (corrupt 2)" in table
    assert "corrupt          catalog_0.catalog line 4, catalog_0.catalog line 8" in table
    assert json.loads(json.dumps(report.as_dict()))["corrupt"] == report.corrupt
    with open(tmp_path / "rows.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["index"]) for r in rows] == list(range(12))  # every record, in index order
    assert rows[3]["skipped"] == "corrupt (catalog_0.catalog line 4)" and rows[3]["pilot_angle"] == ""
    assert rows[7]["skipped"] == "corrupt (catalog_0.catalog line 8)"
    assert all(r["skipped"] == "" and r["pilot_angle"] != "" for i, r in enumerate(rows) if i not in (3, 7))


def test_csv_lists_skipped_records_with_their_reason(tmp_path):
    path = record_tub(tmp_path / "tub", ticks=6, holes={2: "user/angle", 5: "cam/image_array"})
    report = replay(path, lambda image: (0.0, 0.0), csv_path=tmp_path / "rows.csv")
    with open(tmp_path / "rows.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["index"], r["skipped"]) for r in rows] == [
        ("0", ""),
        ("1", "no_user_values"),
        ("2", ""),
        ("3", ""),
        ("4", "no_image"),
        ("5", ""),
    ]
    stamps = {r["_index"]: r["_timestamp_ms"] for r in Tub(path)}
    assert rows[1]["timestamp_ms"] == repr(stamps[1]) and rows[1]["angle_err"] == ""
    assert report.skipped == {"no_image": 1, "no_user_values": 1}


def test_a_tub_with_nothing_playable_gives_an_empty_report(tmp_path):
    holes = {k: "user/angle" for k in range(1, 6)}
    path = record_tub(tmp_path / "tub", ticks=5, holes=holes)
    report = replay(path, lambda image: (0.0, 0.0))
    assert report.records == 0 and report.skipped == {"no_user_values": 5}
    assert report.angle_mae is None and report.inference_ms == {}
    assert json.loads(json.dumps(report.as_dict()))["angle_mae"] is None
    assert "n/a" in report.format_table()


# ------------------------------------------------------------------------------------- CSV, determinism
def test_csv_rows_are_exact_and_two_replays_are_identical(recorded, model, tmp_path):
    a = replay(recorded, model, csv_path=tmp_path / "a.csv")
    b = replay(recorded, model, csv_path=tmp_path / "b.csv")
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    assert a.rows == b.rows
    variable = {"inference_ms", "real_s"}  # real compute time; everything else is the same
    assert {k: v for k, v in a.as_dict().items() if k not in variable} == {
        k: v for k, v in b.as_dict().items() if k not in variable
    }
    with open(tmp_path / "a.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) == 1 + a.records
    stamps = [r["_timestamp_ms"] for r in Tub(recorded)]
    for text, row, stamp in zip(rows[1:], a.rows, stamps, strict=True):
        idx, ts, ua, pa, ut, pt, ae, te, skipped = text
        assert int(idx) == row.index and int(ts) == stamp and skipped == ""
        # the text reads back to the very same floats
        assert (float(ua), float(pa), float(ut), float(pt)) == (
            row.user_angle,
            row.pilot_angle,
            row.user_throttle,
            row.pilot_throttle,
        )
        assert float(ae) == abs(float(pa) - float(ua)) and float(te) == abs(float(pt) - float(ut))


# ------------------------------------------------------------------------------------- library errors
def test_library_errors_name_what_is_wrong(tmp_path, recorded):
    with pytest.raises(TubNotFoundError, match=r"no such file or directory: .*nope"):
        replay(tmp_path / "nope", lambda image: (0.0, 0.0))
    with pytest.raises(ReplayError, match="records no cam/depth"):
        replay(recorded, lambda image: (0.0, 0.0), image_key="cam/depth")

    def failing(image):
        raise RuntimeError("boom")

    with pytest.raises(ReplayError, match=r"record 0: pilot failing failed on a 120x160x3 uint8 frame: boom"):
        replay(recorded, failing)
    with pytest.raises(ReplayError, match=r"record 0: .*returned 0.5; expected \(angle, throttle\)"):
        replay(recorded, lambda image: 0.5)


# ------------------------------------------------------------------------------------------------ CLI
@pytest.mark.subprocess
def test_cli_table_json_and_csv_match_the_library(recorded, model, tmp_path):
    lib = replay(recorded, model, csv_path=tmp_path / "lib.csv")
    table = run_cli(recorded, "--pilot", model)
    assert table.returncode == 0, table.stderr
    assert "120 scored, 0 skipped" in table.stdout
    assert f"{lib.angle_mae:.4f}" in table.stdout
    assert table.stderr == ""  # no drive-loop report on stderr

    proc = run_cli(recorded, "--pilot", model, "--json", "--csv", tmp_path / "cli.csv")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["records"] == 120 and out["skipped"] == {} and out["corrupt"] == []
    for key in ("angle_mae", "throttle_mae", "angle_max_err", "throttle_max_err", "baseline_angle_mae", "replayed_s"):
        assert out[key] == getattr(lib, key), key
    assert (tmp_path / "cli.csv").read_bytes() == (tmp_path / "lib.csv").read_bytes()


@pytest.mark.subprocess
def test_cli_errors_are_one_line_with_exit_2(recorded, model, tmp_path):
    assert_one_line_error(run_cli(tmp_path / "missing", "--pilot", model), "missing", "no such file or directory")
    (tmp_path / "empty").mkdir()
    assert_one_line_error(run_cli(tmp_path / "empty", "--pilot", model), "empty", "not a tub")
    assert_one_line_error(run_cli(recorded, "--pilot", tmp_path / "nope.onnx"), "nope.onnx", "not found")
    small = write_model(tmp_path / "small.onnx", rows=60, cols=80)
    assert_one_line_error(run_cli(recorded, "--pilot", small), "small.onnx", "[1, 60, 80, 3]", "120x160x3")
    assert_one_line_error(
        run_cli(recorded, "--pilot", model, "--csv", tmp_path / "no_dir" / "rows.csv"), "rows.csv", "directory"
    )
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    assert_one_line_error(run_cli(recorded, "--pilot", tmp_path / "junk.onnx"), "junk.onnx", "cannot load")


# ---------------------------------------------------------------------------------------- long replay
def write_long_tub(path: Path, records: int, rows: int, cols: int) -> Path:
    """``records`` records 50 ms apart, handed straight to TubWriter with the recorded time as ``time_fn``.

    (A Vehicle on the virtual clock holds time while the writer thread writes each record, which costs about a
    millisecond of real time per record; the records and their timestamps are the same either way.)
    """
    drive = Drive(rows, cols)
    stamp = iter(1_700_000_000.0 + k * 0.05 for k in range(records))
    w = TubWriter(
        path, INPUTS, TYPES, queue_size=records + 1, fsync=False, time_fn=lambda: next(stamp), drain_timeout_s=300
    )
    for _ in range(records):
        w.run(*drive.run()[:3])
    w.shutdown()
    assert w.stats.written == records
    return path


@pytest.mark.realtime
def test_ten_minutes_at_20_hz_replay_in_seconds(tmp_path):
    rows, cols = 24, 32  # small frames keep the recording quick; the replay path is the same
    path = write_long_tub(tmp_path / "long", records=12_000, rows=rows, cols=cols)
    model = write_model(tmp_path / "m.onnx", rows, cols)
    t = time.perf_counter()
    report = replay(path, model)
    wall = time.perf_counter() - t
    assert report.records == 12_000
    assert report.replayed_s == pytest.approx(11_999 * 0.05, abs=0.002)  # ten minutes
    assert report.late_ms_max == 0.0
    # 2.5 s on an idle 2-core machine. Each record is handed to the pilot's worker thread and back, and with a
    # busy process on each core every hand-over waits for a core: late in the whole suite so loaded, it took
    # 20.5 s. Ten times faster than the recording is what such a machine still guarantees.
    assert wall < 60, f"{report.replayed_s:.0f} s of recording took {wall:.1f} s to replay"
    print(f"\nreplayed {report.replayed_s:.0f} s ({report.records} records) in {wall:.2f} s")
