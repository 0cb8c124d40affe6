"""``asyncdonkey donkey`` says what is wrong with a Donkeycar car in one line, as ``asyncdonkey run`` does.

``asyncdonkey donkey: error: <file>: <what is wrong>`` and exit status 2, never a traceback, for the mistakes a user
makes moving a car: a model that is not a model or is missing, a syntax error in ``manage.py``, ``config.py`` or
``myconfig.py``, a setting of the wrong type, anything else the car raises. The cars here load their settings with
Donkeycar's own ``load_config`` from the ``complete`` template's ``config.py`` and build their pilot with its
``get_model_by_type``, as the template's ``manage.py`` does; one test runs that template itself.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from asyncdonkey.commands.cli import build_parser, main
from asyncdonkey.commands.drive_options import DRIVE_OPTIONS

from .test_donkey_command import TEMPLATES, create_car

pytestmark = [pytest.mark.donkeycar]

#: what the template's manage.py does, in a few lines: load the settings, build and load the pilot, drive
MINI_MANAGE_PY = """\
import sys
import donkeycar as dk

cfg = dk.load_config(myconfig="myconfig.py")


class Counter:
    def __init__(self):
        self.n = 0

    def run(self):
        self.n += 1
        return self.n


def load_model(kl, model_path):
    kl.load(model_path)


def drive(cfg, model_path=None, model_type=None):
    V = dk.vehicle.Vehicle()
    V.add(Counter(), outputs=["count"])
    if model_path:
        kl = dk.utils.get_model_by_type(model_type, cfg)
        load_model(kl, model_path)
    V.start(rate_hz=cfg.DRIVE_LOOP_HZ, max_loop_count=cfg.MAX_LOOPS)
    with open("result.txt", "w") as f:
        f.write(f"{V.mem['count']} {V.last_report.precise_sleeps is not None}")


if cfg.CAMERA_TYPE == "NOPE":
    raise Exception("Unknown camera type: NOPE")
drive(cfg, *sys.argv[1:])
"""


def make_car(folder: Path, manage_py: str = MINI_MANAGE_PY, **settings: object) -> Path:
    """A car folder: ``manage.py``, the ``complete`` template's ``config.py``, and ``myconfig.py`` setting
    ``settings`` (by default a car that drives 3 ticks at 200 Hz)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manage.py").write_text(manage_py)
    shutil.copyfile(TEMPLATES / "cfg_complete.py", folder / "config.py")
    settings = {"DRIVE_LOOP_HZ": 200, "MAX_LOOPS": 3, "CAMERA_TYPE": "MOCK", **settings}
    (folder / "myconfig.py").write_text("".join(f"{k} = {v!r}\n" for k, v in settings.items()))
    return folder / "manage.py"


def one_error(capsys: pytest.CaptureFixture[str]) -> str:
    """The command's one error line; nothing else it printed on stderr is an error or a traceback."""
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith("asyncdonkey")]
    assert len(lines) == 1, err
    assert lines[0].startswith("asyncdonkey donkey: error: "), lines[0]
    return lines[0].removeprefix("asyncdonkey donkey: error: ")


def donkey(car: Path, *car_args: str, options: tuple[str, ...] = ()) -> int:
    return main(["donkey", "--no-uvloop", *options, str(car), *car_args])


# -- the model ----------------------------------------------------------------------------------------------
def test_a_text_file_as_the_model_names_the_file_and_why(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    (tmp_path / "car" / "models").mkdir()
    (tmp_path / "car" / "models" / "pilot.tflite").write_text("not a model\n")
    assert donkey(car, "models/pilot.tflite", "tflite_linear") == 2
    line = one_error(capsys)
    assert line.startswith("models/pilot.tflite: cannot be loaded as a tflite_linear model: "), line
    assert "Flatbuffer" in line


def test_a_missing_model_names_the_file_and_the_cars_folder(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    assert donkey(car, "models/nope.tflite", "tflite_linear") == 2
    assert one_error(capsys) == f"models/nope.tflite: no such model file (in {car.parent.resolve()})"


def test_a_model_of_the_wrong_kind_for_its_type_names_the_file(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    (tmp_path / "car" / "pilot.onnx").write_bytes(b"\x08\x07")
    assert donkey(car, "pilot.onnx", "tflite_linear") == 2
    assert one_error(capsys) == "pilot.onnx: a tflite_* model type needs a .tflite file"


@pytest.mark.skipif(importlib.util.find_spec("tensorflow") is not None, reason="TensorFlow is installed here")
def test_a_keras_model_without_tensorflow_says_to_install_it_or_use_tflite(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    (tmp_path / "car" / "pilot.h5").write_bytes(b"")
    assert donkey(car, "pilot.h5", "linear") == 2  # Donkeycar: NameError: name 'Input' is not defined
    line = one_error(capsys)
    assert line.startswith("manage.py: the pilot needs tensorflow, which is not installed: pip install tensorflow")
    assert "--type tflite_linear" in line


# -- the car's files ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["manage.py", "config.py", "myconfig.py"])
def test_a_syntax_error_in_a_car_file_names_the_file_and_line(tmp_path, capsys, name):
    car = make_car(tmp_path / "car")
    path = car.parent / name
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines, "DRIVE_LOOP_HZ = = 20", "DRIVE_LOOP_HZ = 20"]) + "\n")
    assert donkey(car) == 2
    assert one_error(capsys) == f"{name}:{len(lines) + 1}: syntax error: invalid syntax"
    assert not (car.parent / "result.txt").exists()


def test_a_missing_config_py_names_it(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    (car.parent / "config.py").unlink()
    assert donkey(car) == 2
    line = one_error(capsys)
    assert line.startswith("manage.py:4: FileNotFoundError: ") and "config.py" in line, line
    assert "(raised at donkeycar/config.py:" in line, line


@pytest.mark.parametrize(
    ("setting", "value", "expected"),
    [
        ("DRIVE_LOOP_HZ", "fast", "expected a finite number > 0, got 'fast' (the drive loop rate in Hz)"),
        ("DRIVE_LOOP_HZ", "20", "expected a number, got text '20' (the drive loop rate in Hz)"),
        ("DRIVE_LOOP_HZ", 0, "expected a finite number > 0, got 0 (the drive loop rate in Hz)"),
        ("DRIVE_LOOP_HZ", None, "expected a finite number > 0, got NoneType None (the drive loop rate in Hz)"),
        (
            "MAX_LOOPS",
            2.5,
            "expected a whole number >= 0, got 2.5 (the number of ticks to drive, or None for no limit)",
        ),
        (
            "MAX_LOOPS",
            "ten",
            "expected a whole number >= 0, got 'ten' (the number of ticks to drive, or None for no limit)",
        ),
    ],
)
def test_a_setting_of_the_wrong_type_names_the_setting_and_its_file(tmp_path, capsys, setting, value, expected):
    car = make_car(tmp_path / "car", **{setting: value})
    assert donkey(car) == 2
    assert one_error(capsys) == f"myconfig.py: {setting}: {expected}"
    assert not (car.parent / "result.txt").exists()


def test_a_setting_only_config_py_sets_is_named_there(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    myconfig = car.parent / "myconfig.py"
    myconfig.write_text(myconfig.read_text().replace("DRIVE_LOOP_HZ = 200\n", ""))
    config = car.parent / "config.py"
    config.write_text(config.read_text().replace("DRIVE_LOOP_HZ = 20\n", "DRIVE_LOOP_HZ = -20\n"))
    assert donkey(car) == 2
    assert one_error(capsys).startswith("config.py: DRIVE_LOOP_HZ: expected a finite number > 0, got -20")


@pytest.mark.realtime
def test_the_command_lines_rate_replaces_a_wrong_setting(tmp_path, capsys):
    car = make_car(tmp_path / "car", DRIVE_LOOP_HZ="fast")
    assert donkey(car, options=("--hz", "200")) == 0
    assert (car.parent / "result.txt").read_text() == "3 False"


def test_any_other_error_names_the_cars_line_and_where_it_was_raised(tmp_path, capsys):
    car = make_car(tmp_path / "car", CAMERA_TYPE="NOPE")
    line_no = MINI_MANAGE_PY.splitlines().index('    raise Exception("Unknown camera type: NOPE")') + 1
    assert donkey(car) == 2
    assert one_error(capsys) == f"manage.py:{line_no}: Exception: Unknown camera type: NOPE"


def test_verbose_prints_the_traceback_before_the_line(tmp_path, capsys):
    car = make_car(tmp_path / "car", CAMERA_TYPE="NOPE")
    assert donkey(car, options=("--verbose",)) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err
    assert err.rstrip().splitlines()[-1].startswith("asyncdonkey donkey: error: manage.py:")


# -- the shared options ---------------------------------------------------------------------------------------
@pytest.mark.realtime
def test_precise_reaches_the_cars_drive(tmp_path, capsys):
    car = make_car(tmp_path / "car")
    assert donkey(car, options=("--precise",)) == 0
    assert (car.parent / "result.txt").read_text() == "3 True"


def _option_help(command: str) -> dict[str, str]:
    """``{dest: "--opt METAVAR: help"}`` for the command's options."""
    sub = build_parser()._subparsers._group_actions[0].choices[command]  # type: ignore[union-attr]
    return {
        a.dest: f"{' '.join(a.option_strings)} {a.metavar or ''}: {a.help}".replace("  ", " ")
        for a in sub._actions
        if a.option_strings
    }


def test_run_and_donkey_share_one_definition_of_the_drive_options():
    run, donkey_ = _option_help("run"), _option_help("donkey")
    for dest in DRIVE_OPTIONS:
        assert dest in run and dest in donkey_, dest
        if dest != "hz":  # the rate's default differs: the car file's DRIVE_LOOP_HZ, the car's config
            assert run[dest] == donkey_[dest], dest
    assert run["max_loops"].startswith("--max-loops N:")


def test_a_bad_option_value_is_the_same_error_in_both_commands(capsys):
    for command in ("run", "donkey"):
        with pytest.raises(SystemExit) as done:
            main([command, "--max-loops", "-1", "manage.py"])
        assert done.value.code == 2
        err = capsys.readouterr().err.strip()
        assert err == (
            f"asyncdonkey {command}: error: argument --max-loops: expected a whole number >= 0, got '-1' "
            f"(see asyncdonkey {command} --help)"
        )


# -- the template itself ------------------------------------------------------------------------------------
DRIVE_TEXT_MODEL = ["drive", "--model", "models/pilot.tflite", "--type", "tflite_linear"]


@pytest.mark.subprocess
def test_the_complete_templates_car_with_a_text_file_as_its_model_is_one_line(tmp_path):
    manage_py = create_car(tmp_path / "mycar", CAMERA_TYPE="MOCK", DRIVE_TRAIN_TYPE="MOCK")
    (tmp_path / "mycar" / "models" / "pilot.tflite").write_text("not a model\n")
    done = subprocess.run(
        [str(Path(sys.executable).parent / "asyncdonkey"), "donkey", "--no-uvloop", str(manage_py), *DRIVE_TEXT_MODEL],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "Traceback" not in done.stdout + done.stderr
    [line] = [line for line in done.stderr.splitlines() if line.startswith("asyncdonkey")]
    assert line == (
        "asyncdonkey donkey: error: models/pilot.tflite: cannot be loaded as a tflite_linear model: "
        "The model is not a valid Flatbuffer buffer"
    )
