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

CLI = [sys.executable, "-m", "asyncdonkey.cli"]


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


def test_version():
    proc = run_cli("--version")
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"asyncdonkey {asyncdonkey.__version__}"


def test_missing_file(tmp_path):
    assert_one_line_error(run_cli("run", str(tmp_path / "nope.py")), "nope.py", "not found")


def test_syntax_error_names_file_and_line(tmp_path):
    car = write(tmp_path, "car.py", "import math\ndef build(:\n    pass\n")
    assert_one_line_error(run_cli("run", str(car)), "car.py:2", "syntax error")


def test_no_build(tmp_path):
    car = write(tmp_path, "car.py", "X = 1\n")
    assert_one_line_error(run_cli("run", str(car)), "defines no build() function")


def test_wrong_return_type(tmp_path):
    car = write(tmp_path, "car.py", "def build():\n    return 42\n")
    assert_one_line_error(run_cli("run", str(car)), "build() returned int, expected an asyncdonkey.Vehicle")


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


def test_run_with_max_loops_and_car_args(tmp_path):
    car = write(tmp_path, "car.py", CAR)
    marker = tmp_path / "shutdown.txt"
    proc = run_cli("run", str(car), "--max-loops", "7", "--no-uvloop", "--", str(marker))
    assert proc.returncode == 0, proc.stderr
    assert marker.read_text() == "neutral after 7 ticks"
    assert "Part Profile Summary" in proc.stderr and "loops: 7" in proc.stderr


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
