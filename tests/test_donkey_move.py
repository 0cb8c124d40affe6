"""Moving a Donkeycar car to asyncdonkey, as docs/donkeycar.md tells it: the ``donkeycar-cli`` extra makes
Donkeycar's own ``donkey createcar`` and its templates work without TensorFlow; a car whose camera module is
missing gets one line saying what to do; a ``.tflite`` pilot (float or quantized) drives without TensorFlow.

Everything runs Donkeycar's installed code: its command, its templates, its ``get_model_by_type`` and pilots.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import sys
from pathlib import Path

import donkeycar
import donkeycar.parts.interpreter
import donkeycar.utils
import numpy as np
import pytest
from donkeycar.config import Config
from donkeycar.parts.tub_v2 import Tub as DkTub
from PIL import Image

from asyncdonkey.commands.donkey_tflite import tflite_pilots_replaced
from asyncdonkey.parts.tflite_pilot import TflitePilot

from .test_donkey_command import LOOPBACK_ONLY, TEMPLATES, create_car, drive_through_the_web_page, free_port

pytestmark = [pytest.mark.donkeycar]

MODELS = Path(__file__).parent / "models"
BIN = Path(sys.executable).parent
DRIVE_TFLITE = ["drive", "--model", "models/pilot.tflite", "--type", "tflite_linear"]
#: what the car's process sees: no TensorFlow, whether or not this machine has it
NO_TENSORFLOW = "import sys\nsys.modules['tensorflow'] = None\n"


def car_env(tmp_path: Path) -> dict[str, str]:
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(LOOPBACK_ONLY + NO_TENSORFLOW)
    return {**os.environ, "PYTHONPATH": str(site)}


# -- the extra: Donkeycar's own command and templates ----------------------------------------------------------
@pytest.mark.subprocess
@pytest.mark.parametrize("template", ["complete", "basic"])
def test_donkey_createcar_and_the_cars_command_line_work_with_the_extra(tmp_path, template):
    car = tmp_path / "mycar"
    made = subprocess.run(
        [str(BIN / "donkey"), "createcar", "--path", str(car), "--template", template],
        env=car_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert made.returncode == 0, made.stdout + made.stderr
    assert {"manage.py", "config.py", "myconfig.py", "data", "models"} <= {p.name for p in car.iterdir()}
    helped = subprocess.run(
        [sys.executable, "manage.py", "drive", "--help"],
        cwd=car,
        env=car_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert helped.returncode == 0, helped.stdout + helped.stderr
    usage = helped.stdout[helped.stdout.index("Usage:") :]  # after Donkeycar's banner: the template's docopt usage
    assert "manage.py" in usage and "drive" in usage and "--model=<model>" in usage


# -- a missing camera module: one line ------------------------------------------------------------------------
def run_command(tmp_path: Path, manage_py: Path, *, missing: str = "", module: str = "") -> subprocess.CompletedProcess:
    """``asyncdonkey donkey manage.py drive`` as a user runs it, in a process where ``missing`` cannot be
    imported (as on a PC, or in a venv made without the system's packages), or where ``picamera2`` is the
    source ``module``."""
    env = car_env(tmp_path)
    site = Path(env["PYTHONPATH"])
    if missing:
        custom = site / "sitecustomize.py"
        custom.write_text(custom.read_text() + f"sys.modules[{missing!r}] = None\n")
    if module:
        (site / "picamera2.py").write_text(module)
    return subprocess.run(
        [str(BIN / "asyncdonkey"), "donkey", "--no-uvloop", str(manage_py), "drive"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def asyncdonkey_lines(err: str) -> list[str]:
    """The command's own lines (Donkeycar's banner and logging aside); each must be an error line."""
    lines = [line for line in err.splitlines() if line.startswith("asyncdonkey")]
    assert all(line.startswith("asyncdonkey donkey: error: manage.py: ") for line in lines), lines
    return lines


@pytest.mark.subprocess
def test_a_missing_picamera2_is_one_line_naming_the_setting_and_both_answers(tmp_path):
    manage_py = create_car(tmp_path / "mycar", DRIVE_TRAIN_TYPE="MOCK")  # the template's camera: PICAM
    done = run_command(tmp_path, manage_py, missing="picamera2")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    [line] = asyncdonkey_lines(done.stderr)
    assert 'CAMERA_TYPE = "PICAM"' in line and "picamera2" in line
    assert 'CAMERA_TYPE = "MOCK"' in line and "myconfig.py" in line
    assert "sudo apt install python3-picamera2" in line and "--system-site-packages" in line


#: picamera2 on a Pi whose venv has numpy 2 and sees apt's simplejpeg, built for numpy 1: what numpy raises
NUMPY_1_SIMPLEJPEG = (
    "raise ValueError('numpy.dtype size changed, may indicate binary incompatibility. Expected 96 from C header, "
    "got 88 from PyObject')\n"
)


@pytest.mark.subprocess
def test_picamera2_built_for_numpy_1_is_one_line_naming_simplejpeg(tmp_path):
    manage_py = create_car(tmp_path / "mycar", DRIVE_TRAIN_TYPE="MOCK")
    done = run_command(tmp_path, manage_py, module=NUMPY_1_SIMPLEJPEG)
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    [line] = asyncdonkey_lines(done.stderr)
    assert "numpy.dtype size changed" in line and "pip install --force-reinstall --no-deps simplejpeg" in line


@pytest.mark.subprocess
def test_the_line_names_the_cars_own_drivetrain_setting(tmp_path):
    manage_py = create_car(tmp_path / "mycar", CAMERA_TYPE="MOCK", DRIVE_TRAIN_TYPE="PWM_STEERING_THROTTLE")
    done = run_command(tmp_path, manage_py, missing="Adafruit_PCA9685")
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    [line] = asyncdonkey_lines(done.stderr)
    assert 'DRIVE_TRAIN_TYPE = "PWM_STEERING_THROTTLE"' in line and "Adafruit_PCA9685" in line
    assert 'DRIVE_TRAIN_TYPE = "MOCK"' in line


# -- .tflite pilots without TensorFlow -------------------------------------------------------------------------
def template_config() -> Config:
    cfg = Config()
    cfg.from_pyfile(str(TEMPLATES / "cfg_complete.py"))
    return cfg


def frames() -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    ramp = np.broadcast_to(np.linspace(0, 255, 160, dtype=np.uint8)[None, :, None], (120, 160, 3)).copy()
    return [ramp, rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)]


@pytest.mark.parametrize(
    ("model", "tolerance"),
    [("donkey_small.tflite", 1e-5), ("donkey_small.uint8.tflite", 2e-3), ("donkey_small.int8.tflite", 2e-3)],
)
def test_donkeycars_own_pilot_runs_a_tflite_model_float_or_quantized(model, tolerance):
    """Donkeycar's ``get_model_by_type('tflite_linear')`` pilot, as ``manage.py drive`` builds it under the
    command, gives what asyncdonkey's own TflitePilot gives (a separate code path: it quantizes the uint8 frame,
    Donkeycar's pilot the normalised one); the quantized models agree within a few output steps."""
    with tflite_pilots_replaced():
        pilot = donkeycar.utils.get_model_by_type("tflite_linear", template_config())
    pilot.load(str(MODELS / model))
    ours = TflitePilot(MODELS / model, offload=False)
    for frame in frames():
        angle, throttle = pilot.run(frame)
        ref_angle, ref_throttle = ours.predict(frame)
        assert abs(ref_angle) > 0.01 and abs(ref_throttle) > 0.01  # the frames give the model something to do
        assert angle == pytest.approx(ref_angle, abs=tolerance)
        assert throttle == pytest.approx(ref_throttle, abs=tolerance)
    assert donkeycar.utils.get_model_by_type.__module__ == "donkeycar.utils"  # put back


def test_donkeycars_unchanged_interpreter_refuses_a_quantized_model():
    """Why the command swaps the interpreter in: Donkeycar feeds float32 to a uint8 input."""
    pilot = donkeycar.utils.get_model_by_type("tflite_linear", template_config())
    assert type(pilot.interpreter) is donkeycar.parts.interpreter.TfLite
    pilot.load(str(MODELS / "donkey_small.uint8.tflite"))
    with pytest.raises(ValueError, match="UINT8"):
        pilot.run(frames()[0])


def test_other_model_types_are_left_to_donkeycar():
    with tflite_pilots_replaced():
        pilot = donkeycar.utils.get_model_by_type("tflite_categorical", template_config())
        assert type(pilot.interpreter).__name__ == "LiteRtTfLite"
        # a non-tflite type is Donkeycar's own call through (Keras: without TensorFlow it cannot even build)
        assert donkeycar.parts.interpreter.TfLite.__name__ == "TfLite"


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.subprocess
def test_a_car_drives_on_a_tflite_pilot_without_tensorflow(tmp_path):
    """``asyncdonkey donkey manage.py drive --model models/pilot.tflite --type tflite_linear`` with TensorFlow
    unimportable: the web page switches to the pilot with recording on, and every record carries the pilot's
    angle and throttle for the camera's frame (the image-list camera: one JPEG)."""
    port = free_port()
    car = tmp_path / "mycar"
    images = tmp_path / "images"
    images.mkdir()
    Image.fromarray(frames()[0]).save(images / "0_frame.jpg", quality=95)
    seen = np.asarray(Image.open(images / "0_frame.jpg"))  # what the camera gives the pilot
    manage_py = create_car(
        car,
        CAMERA_TYPE="IMAGE_LIST",
        PATH_MASK=str(images / "*.jpg"),
        DRIVE_TRAIN_TYPE="MOCK",
        USE_JOYSTICK_AS_DEFAULT=False,
        WEB_CONTROL_PORT=port,
        RECORD_DURING_AI=True,
        DRIVE_LOOP_HZ=50,
        MAX_LOOPS=100,
    )
    shutil.copyfile(MODELS / "donkey_small.tflite", car / "models" / "pilot.tflite")
    proc = subprocess.Popen(
        [str(BIN / "asyncdonkey"), "donkey", str(manage_py), *DRIVE_TFLITE],
        cwd=tmp_path,
        env=car_env(tmp_path),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        command = {"angle": 0.0, "throttle": 0.0, "drive_mode": "local", "recording": True}
        asyncio.run(drive_through_the_web_page(port, proc, command, timeout=30, after_s=0.5))
        out, _ = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert "interpreter: TfLite (LiteRT, asyncdonkey)" in out, out
    assert "stopped by: loop limit reached (max_loop_count)" in out, out
    # beside Donkeycar's <hostname>.local line, the addresses of this machine's interfaces, .local, then loopback
    listed = out[out.index("LocalWebController (Donkeycar's), from a phone on the car's network:") :].splitlines()
    urls = [line.split()[0] for line in listed[1:] if line.startswith("  http://")]
    assert urls and all(u.endswith(f":{port}/drive") for u in urls), listed[:5]
    assert ".local:" in urls[-2] and urls[-1] == f"http://127.0.0.1:{port}/drive", listed[:5]
    ref_angle, ref_throttle = TflitePilot(MODELS / "donkey_small.tflite", offload=False).predict(seen)
    tub = DkTub(str(car / "data"), read_only=True)
    try:
        records = list(tub)
    finally:
        tub.close()
    assert 0 < len(records) < 100
    for r in records:
        assert r["user/mode"] == "local"
        assert r["pilot/angle"] == pytest.approx(ref_angle, abs=1e-5)
        assert r["pilot/throttle"] == pytest.approx(ref_throttle, abs=1e-5)
