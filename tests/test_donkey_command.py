"""``asyncdonkey donkey``: a Donkeycar car's own manage.py, unchanged, driving on asyncdonkey's loop.

The end-to-end test makes a car as ``donkey createcar`` does (the installed ``complete`` template and its config)
with a mock camera and drivetrain, runs ``asyncdonkey donkey manage.py drive`` in a subprocess for a bounded
number of loops, drives it through its own web controller's websocket (as the browser page does) and reads the
tub back with Donkeycar's own ``Tub``.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import donkeycar
import donkeycar.vehicle
import pytest
from donkeycar.parts.tub_v2 import Tub as DkTub
from tornado.websocket import websocket_connect

import asyncdonkey
from asyncdonkey.commands.cli import main
from asyncdonkey.commands.donkey import DonkeycarVehicle, DriveOptions, run_manage_py

pytestmark = [pytest.mark.donkeycar]

TEMPLATES = Path(donkeycar.__file__).parent / "templates"


def create_car(path: Path, template: str = "complete", **overrides: object) -> Path:
    """What ``donkey createcar --path PATH --template TEMPLATE`` makes (Donkeycar's management/base.py), plus
    ``overrides`` appended to myconfig.py as a user would set them."""
    for folder in ("models", "data", "logs"):
        (path / folder).mkdir(parents=True, exist_ok=True)
    shutil.copyfile(TEMPLATES / f"{template}.py", path / "manage.py")
    shutil.copyfile(TEMPLATES / f"cfg_{template}.py", path / "config.py")
    shutil.copyfile(TEMPLATES / "train.py", path / "train.py")
    shutil.copyfile(TEMPLATES / "calibrate.py", path / "calibrate.py")
    # myconfig.py: the template, then every line of config.py from `import os` on, commented out
    lines = (path / "config.py").read_text().splitlines(keepends=True)
    start = next(i for i, line in enumerate(lines) if "import os" in line)
    myconfig = (TEMPLATES / "myconfig.py").read_text() + "".join("# " + line for line in lines[start:])
    myconfig += "\n" + "".join(f"{k} = {v!r}\n" for k, v in overrides.items())
    (path / "myconfig.py").write_text(myconfig)
    return path / "manage.py"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# Donkeycar's LocalWebController listens on every interface (tornado's listen(port)); the car runs unchanged,
# so the test process's tornado is told to listen on loopback only.
LOOPBACK_ONLY = """
import tornado.web

_listen = tornado.web.Application.listen


def _loopback_listen(self, port, address=None, **kwargs):
    return _listen(self, port, address or "127.0.0.1", **kwargs)


tornado.web.Application.listen = _loopback_listen
"""


async def drive_through_the_web_page(
    port: int, proc: subprocess.Popen, command: dict, timeout: float, after_s: float = 0.0
) -> None:
    """Send ``command`` on the car's /wsDrive websocket (what its browser page does) ``after_s`` seconds after
    the server accepted the connection."""
    deadline = time.monotonic() + timeout
    while True:
        if proc.poll() is not None:
            raise AssertionError("the car exited before its web controller accepted a connection")
        try:
            ws = await websocket_connect(f"ws://127.0.0.1:{port}/wsDrive", connect_timeout=1)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)
    await asyncio.sleep(after_s)
    await ws.write_message(json.dumps(command))
    await asyncio.sleep(0.2)  # let the server read it before the socket closes
    ws.close()


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.subprocess
def test_a_donkeycar_car_drives_unchanged_with_one_command(tmp_path):
    port = free_port()
    car = tmp_path / "mycar"
    manage_py = create_car(
        car,
        CAMERA_TYPE="MOCK",
        DRIVE_TRAIN_TYPE="MOCK",
        USE_JOYSTICK_AS_DEFAULT=False,
        WEB_CONTROL_PORT=port,
        DRIVE_LOOP_HZ=50,
        MAX_LOOPS=100,
    )
    pristine = manage_py.read_bytes()
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(LOOPBACK_ONLY)
    env = {**os.environ, "PYTHONPATH": str(site)}
    script = Path(sys.executable).with_name("asyncdonkey")
    # run from elsewhere: the command runs the car in its own directory, where Donkeycar finds its config
    proc = subprocess.Popen(
        [str(script), "donkey", str(manage_py), "drive"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        command = {"angle": 0.25, "throttle": 0.3, "drive_mode": "user", "recording": True}
        # half a second into the car's two: its ticks have started by then (the web server's thread starts
        # just before them, and a command read before the first tick would record from the first loop)
        asyncio.run(drive_through_the_web_page(port, proc, command, timeout=20, after_s=0.5))
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    # asyncdonkey's report, the car's own prints, and a prompt end (the web server stopped, not abandoned)
    assert "loops: 100 in" in out, out
    assert "achieved:" in out and "stopped by: loop limit reached (max_loop_count)" in out, out
    assert "You can now go to" in out
    assert "abandoned" not in out, out
    assert manage_py.read_bytes() == pristine

    tub = DkTub(str(car / "data"), read_only=True)
    try:
        records = list(tub)
    finally:
        tub.close()
    # recording began when the web page said so, and went on to the last loop
    assert 0 < len(records) < 100
    assert [r["_index"] for r in records] == list(range(len(records)))
    for r in records:
        assert (r["user/angle"], r["user/throttle"], r["user/mode"]) == (0.25, 0.3, "user")
        image = car / "data" / "images" / r["cam/image_array"]
        assert image.is_file() and image.stat().st_size > 0


# -- the adapter, in process ---------------------------------------------------------------------------------
MINI_CAR = '''
"""A minimal Donkeycar-style car: builds dk.vehicle.Vehicle() and starts it, like the templates."""
import sys

import donkeycar as dk
from donkeycar.parts.transform import Lambda

class Counter:
    def __init__(self):
        self.n = 0
    def run(self):
        self.n += 1
        if self.n == FAIL_AT:
            raise RuntimeError("sensor unplugged")
        return self.n

FAIL_AT = int(sys.argv[2]) if len(sys.argv) > 2 else -1
V = dk.vehicle.Vehicle()
V.add(Counter(), outputs=["count"])
V.add(Lambda(lambda c: c * 2), inputs=["count"], outputs=["double"])
RESULT = V.start(rate_hz=200, max_loop_count=int(sys.argv[1]))
with open("result.txt", "w") as f:
    f.write(f"{type(V).__mro__[1].__name__} {RESULT[0]} {V.mem['double']}")
'''


@pytest.mark.realtime
def test_run_manage_py_puts_our_vehicle_in_place_and_restores_everything(tmp_path, monkeypatch):
    car = tmp_path / "car"
    car.mkdir()
    (car / "manage.py").write_text(textwrap.dedent(MINI_CAR))
    monkeypatch.chdir(tmp_path)
    argv, path = list(sys.argv), list(sys.path)
    options = run_manage_py(car / "manage.py", ["5"], DriveOptions(use_uvloop=False))
    assert (car / "result.txt").read_text() == "DonkeycarVehicle 5 10"  # ran in the car's directory
    assert [r.loops for r in options.reports] == [5]
    assert options.reports[0].stop_reason == "max_loop_count"
    assert (Path.cwd(), sys.argv, sys.path) == (tmp_path, argv, path)
    assert donkeycar.vehicle.Vehicle is not asyncdonkey.Vehicle
    assert not issubclass(donkeycar.vehicle.Vehicle, asyncdonkey.Vehicle)


@pytest.mark.realtime
def test_command_line_options_override_the_cars_start_arguments(tmp_path):
    car = tmp_path / "car"
    car.mkdir()
    (car / "manage.py").write_text(textwrap.dedent(MINI_CAR))
    options = run_manage_py(car / "manage.py", ["1000"], DriveOptions(max_loop_count=3, use_uvloop=False))
    assert (car / "result.txt").read_text() == "DonkeycarVehicle 3 6"
    assert options.reports[0].loops == 3


@pytest.mark.realtime
def test_a_failing_part_stops_the_car_and_exits_1(tmp_path, capsys):
    car = tmp_path / "car"
    car.mkdir()
    (car / "manage.py").write_text(textwrap.dedent(MINI_CAR))
    assert main(["donkey", "--no-uvloop", str(car / "manage.py"), "50", "3"]) == 1
    err = capsys.readouterr().err
    assert "part 'Counter' failed on tick 2" in err and "sensor unplugged" in err
    assert not (car / "result.txt").exists()  # start() raised: the car did not carry on as if it had ended


@pytest.mark.realtime
def test_the_report_of_a_drive_that_failed_is_kept(tmp_path):
    car = tmp_path / "car"
    car.mkdir()
    (car / "manage.py").write_text(textwrap.dedent(MINI_CAR))
    options = DriveOptions(use_uvloop=False)
    with pytest.raises(asyncdonkey.PartError, match="sensor unplugged") as err:
        run_manage_py(car / "manage.py", ["50", "4"], options)
    assert [r.stop_reason for r in options.reports] == ["error"]
    assert err.value.report is options.reports[0] and options.reports[0].loops == 3


def test_a_missing_car_file_is_a_usage_error(tmp_path, capsys):
    assert main(["donkey", str(tmp_path / "nope" / "manage.py"), "drive"]) == 2
    assert "not found" in capsys.readouterr().err


def test_remove_takes_the_part_or_its_entry():
    v = DonkeycarVehicle()
    a, b = object.__new__(_Part), object.__new__(_Part)
    v.add(a, outputs=["a"])
    v.add(b, outputs=["b"])
    v.remove(a)
    assert [e.part for e in v.parts] == [b]
    v.remove(v.parts[0])
    assert v.parts == []
    with pytest.raises(ValueError, match="not a part of this vehicle"):
        v.remove(a)


class _Part:
    def run(self) -> int:
        return 1
