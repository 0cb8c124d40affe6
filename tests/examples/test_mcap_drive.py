"""MCAP recordings in the rest of the tool chain: replay from an MCAP equals replay from the tub of the same
drive, ``convert`` both ways (Donkeycar's reader opens the tub made from an MCAP), and ``report`` draws the
loop's timing with overruns and skipped deadlines marked."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey import Vehicle
from asyncdonkey.commands.cli import main as cli_main
from asyncdonkey.commands.convert import convert
from asyncdonkey.commands.replay import replay
from asyncdonkey.commands.report import load_timing, render_html
from asyncdonkey.parts.mcap import McapRecorder
from asyncdonkey.parts.mcap.reader import McapTub, decode_image, read_mcap
from asyncdonkey.parts.tub import Tub
from asyncdonkey.testing import VirtualClockLoop

from .example_loader import load_example

with contextlib.redirect_stdout(io.StringIO()):
    from donkeycar.parts.tub_v2 import Tub as DkTub

car_py = load_example("car")
CLI = [sys.executable, "-m", "asyncdonkey.commands"]


def red_green_pilot(image: np.ndarray) -> tuple[float, float]:
    x = image.astype(np.float64) / 255.0
    return 2.0 * x[..., 0].mean() - 1.0, x[..., 1].mean()


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> tuple[Path, Path]:
    """Three seconds of the simulated car on the virtual clock, recorded to a tub and to MCAP at once."""
    root = tmp_path_factory.mktemp("drive")
    tub, mcap = root / "tub", root / "drive.mcap"
    v, _ = car_py.make_car(pilot="user", record=tub, mcap=mcap, seconds=3.0, status=None)
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        report = runner.run(v.run(rate_hz=20, max_loop_count=1000))
    assert report.loops == 61
    return tub, mcap


def test_replay_from_mcap_equals_replay_from_the_tub_of_the_same_drive(drive):
    tub, mcap = drive
    from_tub = replay(tub, red_green_pilot)
    from_mcap = replay(mcap, red_green_pilot)
    assert from_tub.records == from_mcap.records == len(Tub(tub)) > 50
    assert from_mcap.skipped == from_tub.skipped
    ts_tub = [r.timestamp_ms for r in from_tub.rows]
    ts_mcap = [r.timestamp_ms for r in from_mcap.rows]
    assert np.diff(ts_tub).tolist() == np.diff(ts_mcap).tolist()  # 50 ms apart in both
    for a, b in zip(from_tub.rows, from_mcap.rows, strict=True):
        assert (a.index, a.at_s, a.user_angle, a.user_throttle) == (b.index, b.at_s, b.user_angle, b.user_throttle)
        assert (a.pilot_angle, a.pilot_throttle) == (b.pilot_angle, b.pilot_throttle)  # the very same pixels
    assert from_tub.angle_mae == from_mcap.angle_mae


def test_simulated_ticks_read_back_whole_milliseconds_apart_whatever_the_wall_clock(tmp_path, monkeypatch):
    """On the virtual clock, ticks 50 ms apart read back 50 ms apart from the tub and from the MCAP, also when
    the wall clock at the first record stands half a millisecond past a whole one: the edge where rounding
    the anchor plus the tick's time made steps of 49 and 51 ms, by float error."""
    real_ns = time.time_ns

    def half_past_ns() -> int:
        return real_ns() // 1_000_000 * 1_000_000 + 500_000

    monkeypatch.setattr(time, "time_ns", half_past_ns)
    monkeypatch.setattr(time, "time", lambda: half_past_ns() / 1e9)
    tub, mcap = tmp_path / "tub", tmp_path / "drive.mcap"
    v, _ = car_py.make_car(pilot="user", record=tub, mcap=mcap, seconds=2.0, status=None)
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        runner.run(v.run(rate_hz=20, max_loop_count=1000))
    for source in (tub, mcap):
        stamps = [r.timestamp_ms for r in replay(source, red_green_pilot).rows]
        assert len(stamps) > 30
        assert set(np.diff(stamps).tolist()) == {50}, source


@pytest.mark.subprocess
def test_the_replay_command_takes_an_mcap_file_and_a_model(drive, tmp_path):
    _, mcap = drive
    out = subprocess.run(
        [*CLI, "replay", str(mcap), "--pilot", str(car_py.DEFAULT_MODEL), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)
    assert report["records"] == 61 and report["tub"] == str(mcap)
    assert report["angle_mae"] < 0.5  # the shipped pilot follows the scripted driver it learnt from


@pytest.mark.donkeycar
def test_convert_mcap_to_a_tub_that_donkeycar_reads(drive, tmp_path):
    _, mcap = drive
    out = tmp_path / "from_mcap"
    res = convert(mcap, out, only_when="recording")
    assert res.records == 61
    assert {"cam/image_array", "user/angle", "user/throttle", "user/mode", "sim/cte"} <= set(res.channels)
    src = list(McapTub(mcap).records())
    dk = DkTub(str(out), read_only=True)
    try:
        recs = list(dk)
        assert len(recs) == 61
        for r, s in zip(recs, src, strict=True):
            assert r["user/angle"] == s.raw["user/angle"] and r["user/mode"] == s.raw["user/mode"]
            assert r["_timestamp_ms"] == s.raw["_timestamp_ms"]
        # the JPEG was copied, not re-encoded: the same bytes as in the MCAP file
        assert (out / "images" / recs[5]["cam/image_array"]).read_bytes() == s_image_bytes(src[5])
    finally:
        dk.close()


def s_image_bytes(rec) -> bytes:
    return rec.image_bytes("cam/image_array")


def test_convert_a_tub_to_mcap_and_back(drive, tmp_path):
    tub, _ = drive
    mcap = tmp_path / "tub.mcap"
    res = convert(tub, mcap)
    original = list(Tub(tub))
    assert res.records == len(original)
    msgs = [m for m in read_mcap(mcap, {"/cam/image_array"})]
    assert len(msgs) == len(original)
    first = original[0]
    assert bytes(msgs[0].value.data) == first.image_path("cam/image_array").read_bytes()
    assert np.array_equal(decode_image(msgs[0].value), first["cam/image_array"])
    back = list(McapTub(mcap).records())
    assert [r.raw["user/angle"] for r in back] == [r["user/angle"] for r in original]
    assert [r.raw["_timestamp_ms"] for r in back] == [r["_timestamp_ms"] for r in original]


def test_convert_refuses_to_overwrite_and_says_why(drive, tmp_path, capsys):
    tub, mcap = drive
    assert cli_main(["convert", str(mcap), str(tub)]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and err.count("\n") == 1
    assert cli_main(["convert", str(tmp_path / "nothing"), str(tmp_path / "x.mcap")]) == 2
    assert f"no such file or directory: {tmp_path / 'nothing'}" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not a recording")
    assert cli_main(["convert", str(tmp_path / "notes.txt"), str(tmp_path / "x.mcap")]) == 2
    assert "notes.txt is not a tub directory or an MCAP file" in capsys.readouterr().err


class Stall:
    """A part that stalls the loop on some ticks (virtual time), so ticks overrun and deadlines are skipped."""

    def __init__(self):
        self.k = 0

    async def run(self):
        self.k += 1
        if self.k in (10, 30):
            await asyncio.sleep(0.17)  # 3.4 periods at 20 Hz: an overrun and 2 skipped deadlines
        return self.k


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_report_draws_lateness_with_overruns_and_skipped_deadlines(tmp_path):
    v = Vehicle()
    v.add(Stall(), outputs=["n"], name="stall")
    path = tmp_path / "stall.mcap"
    rec = McapRecorder(path, v, fsync=False)
    v.add(rec, name="mcap")
    report = await v.run(rate_hz=20, max_loop_count=50)
    rec.shutdown()
    assert report.overruns == 2 and report.skipped_deadlines > 0
    d = load_timing(path)
    assert d.t.size == 50 and d.overruns == 2 and d.skipped_deadlines == report.skipped_deadlines
    # each stall ends 0.17 s after its tick started: the next tick starts then, 20 ms late, 2 deadlines skipped
    assert [(round(t, 2), n) for t, n in d.skipped_at] == [(0.62, 2), (1.72, 2)]
    assert np.nanmax(d.duration_ms) == pytest.approx(170, abs=1)
    assert set(d.parts) == {"stall", "mcap"}
    # every tick and part run of the drive, the same figures as its own report
    p = v.profiler
    assert list(d.duration_ms) == list(p.tick.recent(drop_last=False) * 1e3)
    assert list(d.lateness_ms) == list(p.lateness.recent(drop_last=False) * 1e3)
    for name in ("stall", "mcap"):
        assert list(d.parts[name]) == list(p.parts[name].recent(drop_last=False) * 1e3)
    page = render_html(d)
    assert page.count("deadline(s) skipped") == 2 and page.count("overran by") == 2
    for svg in page.split("<svg")[1:]:
        ET.fromstring("<svg" + svg.split("</svg>")[0] + "</svg>")  # well-formed inline SVG
    assert "Lateness histogram" in page and "Time per part" in page


def test_report_command_on_mcap_and_on_a_tub(drive, tmp_path, capsys):
    tub, mcap = drive
    assert cli_main(["report", str(mcap), "-o", str(tmp_path / "r.html")]) == 0
    page = (tmp_path / "r.html").read_text()
    assert "61 ticks" in page and "SimCamera" in page and "McapRecorder" in page
    assert cli_main(["report", str(tub), "-o", str(tmp_path / "t.html")]) == 0
    assert "Record intervals" in (tmp_path / "t.html").read_text()
    capsys.readouterr()
    assert cli_main(["report", str(tmp_path / "r.html")]) == 2
    assert capsys.readouterr().err.startswith("asyncdonkey report: error:")
