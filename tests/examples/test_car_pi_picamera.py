"""examples/car_pi.py with --camera picamera2 (on the picamera2 model) and --camera none."""

import itertools
import sys
from pathlib import Path

import pytest

from asyncdonkey.parts.tub import Tub
from asyncdonkey.testing.camera_models import frame_number
from asyncdonkey.testing.picamera2_model import Picamera2Model

from .example_loader import load_example
from .test_car_pi import Driver, Rig

MODEL = str(Path(__file__).resolve().parents[2] / "examples" / "models" / "sim_pilot.onnx")


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path)
    yield r
    r.close()


def test_the_camera_option_and_its_checks():
    car_pi = load_example("car_pi")
    _, args = car_pi.parse_args([])
    assert args.camera == "opencv"  # what the car did before the option existed
    for bad in (["--camera", "none", "--model", "m.onnx"], ["--camera", "picamera2", "CAMERA_INDEX=/dev/video0"]):
        with pytest.raises(SystemExit):
            car_pi.parse_args(bad)
    cfg, args = car_pi.parse_args(["--camera", "picamera2", "CAMERA_VFLIP=true", "CAMERA_INDEX=1"])
    assert (args.camera, cfg.CAMERA_VFLIP, cfg.CAMERA_HFLIP, cfg.CAMERA_INDEX) == ("picamera2", True, False, 1)


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_with_picamera2_the_car_records_its_frames_and_a_stalled_camera_stops_the_pilot(rig):
    car_pi = load_example("car_pi")
    cam_model = Picamera2Model(fps=20)
    v = car_pi.build(
        rig.argv("HAVE_IMU=false", "CAMERA_INDEX=0", "--camera", "picamera2", "--model", MODEL),
        buses=rig.buses,
        camera_options={"picamera2": cam_model.module, "sensor_clock_ns": cam_model.clock_ns},
    )
    pad = rig.pad
    seen = []

    class Watch:
        def run(self, mode, pilot_throttle, throttle, age):
            seen.append((mode, pilot_throttle, throttle, age))

    def local():  # A twice: user -> local_angle -> local (the pilot drives and sets the throttle)
        pad.click(0)
        pad.click(0)

    v.add(Watch(), inputs=["user/mode", "pilot/throttle", "throttle", "throttle@age"])
    driver = Driver(rig, {2: lambda: pad.press(1), 30: local, 50: cam_model.stall})
    v.add(driver, name="driver")
    report = await v.run(rate_hz=20, max_loop_count=70)
    assert report.loops == 70 and not report.part_errors

    rows = list(Tub(rig.tub))
    numbers = [frame_number(r["cam/image_array"]) for r in rows]
    assert rows and rows[0]["cam/image_array"].shape == (120, 160, 3)
    assert numbers[10] > numbers[0]  # the recorded frames are the camera's, moving on

    driving = seen[35:50]
    assert all(mode == "local" and age < 0.25 for mode, *_, age in driving)  # fresh frames: young commands
    assert len({esc for _, esc in driver.pulses[35:51]}) > 3  # the pilot works the ESC
    stalled = seen[51:]
    assert all(mode == "local" and pilot != 0.0 for mode, pilot, *_ in stalled)  # it still asks to drive...
    assert all(b[3] == pytest.approx(a[3] + 0.05) for a, b in itertools.pairwise(stalled))  # ...on an old frame
    too_old = next(k for k, s in enumerate(seen) if k > 50 and s[3] >= 0.25)
    # PWMThrottle's own failsafe: a command 0.25 s old or more holds the ESC at the stopped pulse (the pulse a
    # tick writes is what the driver sees at the next tick's start)
    assert {esc for _, esc in driver.pulses[too_old + 1 :]} == {370}
    assert driver.pulses[too_old - 1][1] != 370


@pytest.mark.asyncio
@pytest.mark.virtual_clock
async def test_without_a_camera_the_car_drives_and_records_no_images(rig):
    car_pi = load_example("car_pi")
    v = car_pi.build(rig.argv("HAVE_IMU=false", "--camera", "none"), buses=rig.buses)
    v.add(Driver(rig, {2: lambda: rig.pad.press(1)}), name="driver")
    report = await v.run(rate_hz=20, max_loop_count=10)
    assert report.loops == 10 and not report.part_errors
    rows = list(Tub(rig.tub))
    assert rows and "cam/image_array" not in rows[0]


def test_the_cli_says_in_one_line_how_to_install_picamera2(monkeypatch, capsys):
    from asyncdonkey.commands.cli import main

    monkeypatch.setitem(sys.modules, "picamera2", None)
    car = str(Path(__file__).resolve().parents[2] / "examples" / "car_pi.py")
    status = main(["run", car, "--", "--camera", "picamera2"])
    err = capsys.readouterr().err.strip()
    assert status == 2
    assert "Traceback" not in err and len(err.splitlines()) == 1
    assert "sudo apt install python3-picamera2" in err and "--system-site-packages" in err
