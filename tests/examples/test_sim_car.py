"""examples/car.py, the README's `make run`: the simulated car drives laps on the virtual clock."""

import io
from pathlib import Path

import pytest

from asyncdonkey.parts.tub import Tub

from .example_loader import load_example

car_py = load_example("car")


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_scripted_user_drives_two_laps_and_records_them(tmp_path):
    status = io.StringIO()
    v, car = car_py.make_car(pilot="user", record=tmp_path / "tub", seconds=0, laps=2, status=status)
    report = await v.run(rate_hz=20, max_loop_count=20 * 200)
    assert report.stop_reason == "lap target reached (2 laps)"  # not the loop limit
    assert car.sim.laps.laps == 2
    assert car.sim.respawns == 0
    assert report.overruns == 0 and report.skipped_deadlines == 0
    # every tick with the throttle open was recorded, with the driver's commands and the frames
    tub = Tub(tmp_path / "tub")
    records = list(tub)
    assert len(records) == report.loops
    first = records[0]
    assert first["user/mode"] == "user"
    assert first["cam/image_array"].shape == (120, 160, 3)
    assert "pilot/angle" not in first  # no pilot: nothing recorded under its name
    assert all(abs(r["sim/cte"]) < 0.5 for r in records)
    assert records[-1]["sim/laps"] in (1, 2)
    # the status line and the summary were written
    text = status.getvalue()
    assert "drove 2 laps" in text


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_shipped_pilot_drives_three_clean_laps():
    v, car = car_py.make_car(seconds=0, laps=3, status=None)  # the defaults of `make run`: shipped model
    status = next(e.part for e in v.parts if e.name == "Status")
    report = await v.run(rate_hz=20, max_loop_count=20 * 300)
    assert report.stop_reason == "lap target reached (3 laps)"
    assert car.sim.laps.laps == 3
    assert car.sim.respawns == 0 and status.off_track_ticks == 0
    assert status.abs_cte_max < 0.25  # the road is 1 m wide: never near its edge
    assert v.mem["user/mode"] == "local" and v.mem["pilot/angle"] is not None
    assert report.parts["OnnxPilot"]["count"] > 0  # inference ran, and shows in the profiler


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_the_shipped_tflite_pilot_drives_a_clean_lap():
    """`--pilot examples/models/sim_pilot.tflite`: the same pilot converted to TFLite, run by LiteRT."""
    model = Path(car_py.__file__).resolve().parent / "models" / "sim_pilot.tflite"
    v, car = car_py.make_car(pilot=model, seconds=0, laps=1, status=None)
    status = next(e.part for e in v.parts if e.name == "Status")
    report = await v.run(rate_hz=20, max_loop_count=20 * 120)
    assert report.stop_reason == "lap target reached (1 lap)" and car.sim.laps.laps == 1
    assert car.sim.respawns == 0 and status.off_track_ticks == 0
    assert report.parts["TflitePilot"]["count"] > 0


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_stops_after_the_given_seconds_of_runtime_clock():
    v, car = car_py.make_car(pilot="user", seconds=3.0, status=None)
    report = await v.run(rate_hz=20, max_loop_count=10_000)
    assert report.stop_reason == "time limit reached (3 s)"
    assert report.loops == 61  # ticks at 0, 0.05, ... 3.0 s; the one at 3.0 s asks to stop
    assert car.sim.progress > 2.0  # the car moved


def test_car_options_and_their_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"pilot model .*nope.onnx not found"):
        car_py.build(["--pilot", str(tmp_path / "nope.onnx")])
    with pytest.raises(ValueError, match="needs a pilot"):
        car_py.make_car(pilot="user", mode="local", status=None)
    v = car_py.build(["--pilot", "user", "--quiet"])
    names = [e.name for e in v.parts]
    assert names == ["SimCamera", "SimTelemetry", "SimController", "DriveMode", "SimCar", "Status"]


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_laps_option_drives_until_that_many_laps_past_the_default_time():
    v = car_py.build(["--pilot", "user", "--laps", "2", "--quiet"])
    status = next(e.part for e in v.parts if e.name == "Status")
    report = await v.run(rate_hz=20, max_loop_count=20 * 200)
    assert report.stop_reason == "lap target reached (2 laps)"
    assert status.laps == 2
    assert report.loops / 20 > car_py.DEFAULT_SECONDS  # two laps take longer than the default drive


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_seconds_given_explicitly_still_limits_a_laps_drive():
    v = car_py.build(["--pilot", "user", "--laps", "2", "--seconds", "3", "--quiet"])
    report = await v.run(rate_hz=20, max_loop_count=20 * 200)
    assert report.stop_reason == "time limit reached (3 s)" and report.loops == 61  # 3 s, before the first lap


def test_car_option_defaults_and_bad_values(capsys):
    assert car_py.parse_args([]).seconds == car_py.DEFAULT_SECONDS
    assert car_py.parse_args(["--laps", "3"]).seconds == 0.0  # no time limit
    assert car_py.parse_args(["--laps", "3", "--seconds", "90"]).seconds == 90.0
    for bad in (["--laps", "-1"], ["--laps", "1.5"], ["--seconds", "inf"], ["--seconds", "-3"]):
        with pytest.raises(SystemExit) as exc:
            car_py.parse_args(bad)
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert f"argument {bad[0]}: expected" in err and repr(bad[1]) in err


@pytest.mark.parametrize("pilot_mode", ["in-order", "pipelined", "frame"])
@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_every_pilot_mode_drives_a_clean_lap_and_frame_mode_acts_within_the_inference(pilot_mode):
    v, car = car_py.make_car(seconds=0, laps=1, status=None, pilot_mode=pilot_mode)
    status = next(e.part for e in v.parts if e.name == "Status")
    report = await v.run(rate_hz=20, max_loop_count=20 * 120)
    assert car.sim.laps.laps == 1 and car.sim.respawns == 0 and status.off_track_ticks == 0
    assert report.achieved_hz == pytest.approx(20.0)
    latency = report.latency_ms["SimCar"]
    if pilot_mode == "frame":
        # each frame is inferred as it is rendered and the car takes the command at once: on the virtual
        # clock the inference costs no time, so capture to actuation is 0
        assert latency["max"] == pytest.approx(0.0, abs=1e-6)
        assert report.pipelined["OnnxPilot"]["rate_hz"] == pytest.approx(20.0)
    elif pilot_mode == "pipelined":
        # started by the tick with the newest frame (up to a period old), its command reaches the car at the
        # next tick: one more period
        assert 50.0 <= latency["50%"] <= 100.0 + 1e-6
    else:
        # in order: the newest frame (up to a period old), inferred and applied in the same tick
        assert latency["max"] <= 50.0 + 1e-6


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_an_80ms_pilot_slows_the_in_order_loop_but_not_the_frame_started_one():
    rates = {}
    for mode in ("in-order", "frame"):
        v, _car = car_py.make_car(seconds=10, status=None, pilot_mode=mode, pilot_delay=0.08)
        report = await v.run(rate_hz=20, max_loop_count=20 * 20)
        rates[mode] = (report.achieved_hz, report.overruns)
        if mode == "frame":
            p = report.pipelined["OnnxPilot"]
            assert p["rate_hz"] == pytest.approx(1 / 0.08, rel=0.05)  # the pilot at its own rate
            # at most the frame's age when the pilot became free (< one frame period) + the inference
            lat = report.latency_ms["SimCar"]
            assert lat["50%"] >= 80.0 and lat["max"] <= 80.0 + 50.0 + 1e-6
    assert rates["in-order"][0] == pytest.approx(12.5, rel=0.02) and rates["in-order"][1] > 100
    assert rates["frame"] == (pytest.approx(20.0), 0)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_quiet_drops_the_live_line_but_keeps_the_summary():
    """``--quiet`` (``live_status=False``) silences the line redrawn while driving, not the drive's result."""
    texts = {}
    for live in (True, False):
        status = io.StringIO()
        v, _ = car_py.make_car(pilot="user", seconds=11.0, status=status, live_status=live)
        report = await v.run(rate_hz=20, max_loop_count=10_000)
        assert report.stop_reason == "time limit reached (11 s)"
        texts[live] = status.getvalue().splitlines()
    live_lines = [line for line in texts[True] if "lateness p99" in line]
    assert len(live_lines) == 2  # not a terminal: a line every 5 s
    assert not any("lateness p99" in line for line in texts[False])
    assert texts[False] == [texts[True][-1]]  # the summary, the same with and without the live line
    assert texts[False][0].startswith("drove 0 laps")
