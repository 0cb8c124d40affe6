"""`asyncdonkey run` in a subprocess: errors are one line with exit 2; signals shut the car down cleanly."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import asyncdonkey
from asyncdonkey import options
from asyncdonkey.commands import cli

CLI = [sys.executable, "-m", "asyncdonkey.commands"]


def run_cli(*args, timeout=30):
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


def write(tmp_path: Path, name: str, body: str) -> Path:
    p = tmp_path / name
    p.write_text(textwrap.dedent(body))
    return p


def assert_one_line_error(proc, *fragments):
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for f in fragments:
        assert f in lines[0]


@pytest.mark.subprocess
def test_version():
    proc = run_cli("--version")
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"asyncdonkey {asyncdonkey.__version__}"


@pytest.mark.subprocess
def test_missing_file(tmp_path):
    assert_one_line_error(run_cli("run", str(tmp_path / "nope.py")), "nope.py", "not found")


@pytest.mark.subprocess
def test_syntax_error_names_file_and_line(tmp_path):
    car = write(tmp_path, "car.py", "import math\ndef build(:\n    pass\n")
    assert_one_line_error(run_cli("run", str(car)), "car.py:2", "syntax error")


@pytest.mark.subprocess
def test_no_build(tmp_path):
    car = write(tmp_path, "car.py", "X = 1\n")
    assert_one_line_error(run_cli("run", str(car)), "defines no build() function")


@pytest.mark.subprocess
def test_wrong_return_type(tmp_path):
    car = write(tmp_path, "car.py", "def build():\n    return 42\n")
    assert_one_line_error(run_cli("run", str(car)), "build() returned int, expected an asyncdonkey.Vehicle")


@pytest.mark.subprocess
def test_import_error_is_one_line(tmp_path):
    car = write(tmp_path, "car.py", "import no_such_module_xyz\n")
    assert_one_line_error(run_cli("run", str(car)), "ModuleNotFoundError", "no_such_module_xyz")


CAR = """
    import sys
    from pathlib import Path
    from asyncdonkey import Vehicle

    DRIVE_LOOP_HZ = 50

    class Throttle:
        def __init__(self, marker):
            self.marker = marker
            self.n = 0
        def run(self):
            self.n += 1
            if self.n == 5:
                print("DRIVING", flush=True)
            return 0.4
        def shutdown(self):
            Path(self.marker).write_text("neutral after %d ticks" % self.n)

    def build(args):
        v = Vehicle()
        v.add(Throttle(args[0]), outputs=["throttle"])
        return v
"""


@pytest.mark.subprocess
def test_run_with_max_loops_and_car_args(tmp_path):
    car = write(tmp_path, "car.py", CAR)
    marker = tmp_path / "shutdown.txt"
    proc = run_cli("run", str(car), "--max-loops", "7", "--no-uvloop", "--", str(marker))
    assert proc.returncode == 0, proc.stderr
    assert marker.read_text() == "neutral after 7 ticks"
    assert "Part Profile Summary" in proc.stderr and "loops: 7" in proc.stderr


@pytest.mark.subprocess
def test_run_in_precise_mode_on_uvloop(tmp_path):
    car = write(tmp_path, "car.py", CAR)
    marker = tmp_path / "shutdown.txt"
    proc = run_cli("run", str(car), "--max-loops", "5", "--hz", "100", "--precise", "--", str(marker))
    assert proc.returncode == 0, proc.stderr
    assert marker.read_text() == "neutral after 5 ticks"


@pytest.mark.realtime
@pytest.mark.subprocess
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_shuts_down_cleanly_with_final_report(tmp_path, sig):
    car = write(tmp_path, "car.py", CAR)
    marker = tmp_path / "shutdown.txt"
    proc = subprocess.Popen(
        [*CLI, "run", str(car), "--", str(marker)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "DRIVING"
        time.sleep(0.1)
        os.kill(proc.pid, sig)
        _, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert marker.read_text().startswith("neutral after")
    assert f"received {sig.name}: stopping" in err
    assert "Part Profile Summary" in err and f"stopped by: {sig.name}" in err
    assert "achieved: " in err and "of 50 Hz" in err  # DRIVE_LOOP_HZ from the car file


@pytest.mark.subprocess
def test_part_failure_exit_code_and_message(tmp_path):
    car = write(
        tmp_path,
        "car.py",
        """
        from asyncdonkey import Vehicle
        class Bad:
            def run(self):
                raise KeyError("cam/image_array")
        def build():
            v = Vehicle()
            v.add(Bad(), name="camera")
            return v
    """,
    )
    proc = run_cli("run", str(car), "--max-loops", "3")
    assert proc.returncode == 1
    assert "part 'camera' failed on tick 0: KeyError" in proc.stderr.strip().splitlines()[-1]
    assert "Traceback" not in proc.stderr
    verbose = run_cli("run", str(car), "--max-loops", "3", "--verbose")
    assert verbose.returncode == 1
    assert "part 'camera' failed on tick 0: KeyError" in verbose.stderr.strip().splitlines()[-1]
    # the cause's traceback, down to the line of the part that raised
    assert "Traceback (most recent call last)" in verbose.stderr
    assert 'raise KeyError("cam/image_array")' in verbose.stderr


@pytest.mark.subprocess
def test_car_file_with_dataclasses_and_postponed_annotations(tmp_path):
    """The car file is imported like a module (registered in sys.modules), so a dataclass settings object
    under ``from __future__ import annotations`` works as it does in any imported file."""
    car = write(
        tmp_path,
        "settings_car.py",
        """
        from __future__ import annotations
        from dataclasses import dataclass, field
        from asyncdonkey import Vehicle

        @dataclass
        class Settings:
            pins: list[str] = field(default_factory=lambda: ["PCA9685.1:40.1"])

        def build():
            assert Settings().pins == ["PCA9685.1:40.1"]
            return Vehicle()
        """,
    )
    proc = run_cli("run", str(car), "--max-loops", "2", "--no-uvloop")
    assert proc.returncode == 0, proc.stderr
    assert "loops: 2" in proc.stderr


# ------------------------------------------------------------------------------------------- bad values
def run_main(capsys, *argv: str) -> tuple[int, str]:
    """``asyncdonkey <argv>`` in this process: (exit status, stderr). Bad values never get as far as driving."""
    try:
        status = cli.main(list(argv))
    except SystemExit as exc:
        status = exc.code
    return status, capsys.readouterr().err


@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        (["--hz", "inf"], ["argument --hz", "expected a finite number > 0", "'inf'"]),
        (["--hz", "abc"], ["argument --hz", "expected a finite number > 0", "'abc'"]),
        (["--hz", "0"], ["argument --hz", "expected a finite number > 0"]),
        (["--duration", "nan"], ["argument --duration", "expected a finite number > 0", "'nan'"]),
        (["--duration", "-2"], ["argument --duration", "expected a finite number > 0"]),
        (["--max-loops", "1.5"], ["argument --max-loops", "expected a whole number >= 0", "'1.5'"]),
        (["--max-loops", "-1"], ["argument --max-loops", "expected a whole number >= 0"]),
    ],
)
def test_bad_run_options_are_one_line_naming_the_option(tmp_path, capsys, args, fragments):
    car = write(tmp_path, "car.py", "from asyncdonkey import Vehicle\ndef build():\n    return Vehicle()\n")
    status, err = run_main(capsys, "run", str(car), *args)
    assert status == 2
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and "_positive_float" not in err
    for f in fragments:
        assert f in err, err


@pytest.mark.parametrize(
    ("value", "shown"),
    [('"fast"', "'fast'"), ("float('inf')", "inf"), ("0", "0"), ("-20", "-20"), ("None", "None"), ("True", "True")],
)
def test_bad_drive_loop_hz_in_the_car_file_is_one_line(tmp_path, capsys, value, shown):
    car = write(
        tmp_path,
        "car.py",
        f"from asyncdonkey import Vehicle\nDRIVE_LOOP_HZ = {value}\ndef build():\n    return Vehicle()\n",
    )
    status, err = run_main(capsys, "run", str(car), "--max-loops", "1")
    assert status == 2
    line = err.strip()
    assert len(line.splitlines()) == 1 and "Traceback" not in line, err
    assert "car.py: DRIVE_LOOP_HZ: expected a finite number > 0" in line and shown in line


def test_replay_speed_is_checked_by_the_same_rule(tmp_path, capsys):
    for bad in ("inf", "abc", "0"):
        status, err = run_main(capsys, "replay", str(tmp_path), "--pilot", "m.onnx", "--speed", bad)
        assert status == 2
        assert err.strip().splitlines() == [
            f"asyncdonkey replay: error: argument --speed: expected a finite number > 0, got '{bad}' "
            "(see asyncdonkey replay --help)"
        ]


def test_the_option_checks_accept_what_they_should():
    assert options.positive_float("20") == 20.0 and options.positive_float(0.5) == 0.5
    assert options.non_negative_float("0") == 0.0 and options.non_negative_int(" 3 ") == 3
    for check, bad in [
        (options.positive_float, "1e400"),  # overflows to inf
        (options.non_negative_float, "-0.1"),
        (options.non_negative_int, "3.0"),
        (options.non_negative_int, 2.0),
        (options.non_negative_int, False),
    ]:
        with pytest.raises(options.BadValue, match="expected"):
            check(bad)
