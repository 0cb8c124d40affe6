"""A car that refuses to start exits: `asyncdonkey run` as its own process, for each kind of refusal.

Each test runs the car as the user does, ``python -m asyncdonkey.commands run CAR ...``, and asserts the exit
status within a few seconds, the one line that says why, and that what the car had opened is gone afterwards: no
listener left on its port (binding it and connecting to it on 127.0.0.1 both tell), the parts' shutdown run. A
process that hangs instead (a Zenoh session's non-daemon threads kept it alive for an hour and more) fails here
by its timeout, and is killed.
"""

from __future__ import annotations

import errno
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from asyncdonkey.commands.cli import EXIT_GRACE_S

from ..examples.example_loader import EXAMPLES

CLI = [sys.executable, "-m", "asyncdonkey.commands"]
CAR = str(EXAMPLES / "car.py")
#: how long a refused car may take to exit on a loaded 2-core machine (it takes about 1 s: mostly imports)
EXIT_WITHIN_S = 20.0


class Exited:
    """How a car process ended: its status, its stderr lines and how long it ran."""

    def __init__(self, status: int, err: str, seconds: float) -> None:
        self.status, self.err, self.seconds = status, err, seconds
        self.lines = err.strip().splitlines()


def run_car(*args: str) -> Exited:
    """Run ``asyncdonkey ARGS`` and wait for it to exit by itself; a process still running after
    ``EXIT_WITHIN_S`` is killed and the test fails, with what it had said."""
    t0 = time.monotonic()
    proc = subprocess.Popen([*CLI, *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _, err = proc.communicate(timeout=EXIT_WITHIN_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
        pytest.fail(f"asyncdonkey {' '.join(args)} still running {EXIT_WITHIN_S:g} s after it started; said: {err}")
    return Exited(proc.returncode, err, time.monotonic() - t0)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def assert_nothing_listens_on(port: int) -> None:
    """No socket of the car's is left on ``port``: it can be bound (a listener on 0.0.0.0 or 127.0.0.1 would
    refuse that) and nothing accepts a connection there."""
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            pytest.fail(f"port {port} is still taken after the car exited: {exc}")
    with socket.socket() as s:
        s.settimeout(2.0)
        assert s.connect_ex(("127.0.0.1", port)) == errno.ECONNREFUSED, f"something still accepts on port {port}"


def assert_one_line(out: Exited, status: int, *fragments: str) -> str:
    assert out.status == status, out.err
    assert "Traceback" not in out.err, out.err
    assert len(out.lines) == 1, out.err
    for f in fragments:
        assert f in out.lines[0], out.lines[0]
    return out.lines[0]


def write_car(tmp_path: Path, body: str) -> Path:
    car = tmp_path / "car.py"
    car.write_text(textwrap.dedent(body))
    return car


#: a part that listens on 127.0.0.1 (a server on a non-daemon thread, as some libraries start theirs) and
#: opens a pty's serial port when it is made; its shutdown closes both and says so in ``<tmp>/shut``
SERVER_PART = """
    import os
    import socket
    import sys
    import threading
    from pathlib import Path

    import serial

    from asyncdonkey import Vehicle


    class Server:
        def __init__(self, port, marker):
            self.marker = Path(marker)
            self.sock = socket.socket()
            self.sock.bind(("127.0.0.1", port))
            self.sock.listen()
            self.master, slave = os.openpty()
            self.serial = serial.Serial(os.ttyname(slave), timeout=0)
            os.close(slave)
            self.closing = threading.Event()
            self.thread = threading.Thread(target=self.serve, name="server")  # not a daemon: it holds the exit
            self.thread.start()

        def serve(self):
            while not self.closing.wait(0.05):
                pass

        def run(self):
            return None

        def shutdown(self):
            self.closing.set()
            self.sock.close()
            self.serial.close()
            os.close(self.master)
            self.thread.join()
            self.marker.write_text(f"closed: socket {self.sock.fileno()}, serial open {self.serial.is_open}")
"""


# ----------------------------------------------------------------------------------------- the refusals
@pytest.mark.subprocess
@pytest.mark.network
def test_the_zenoh_listen_refusal_exits_2_in_one_line_and_stops_listening() -> None:
    """The documented refusal (a command subscriber on a session listening on every interface without TLS or
    access rules): the session the car's link opened in build() is closed, so the process exits."""
    pytest.importorskip("zenoh")
    port = free_port()
    out = run_car("run", CAR, "--", "--pilot", "remote", "--zenoh-listen", f"tcp/0.0.0.0:{port}")
    assert_one_line(
        out, 2, "asyncdonkey run: error:", "ZenohConfigError", f"listens on tcp/0.0.0.0:{port} without TLS", "refusing"
    )
    assert_nothing_listens_on(port)


@pytest.mark.subprocess
def test_a_value_error_of_the_car_file_exits_2_in_one_line() -> None:
    out = run_car("run", CAR, "--", "--pilot", "remote")
    assert_one_line(
        out, 2, "asyncdonkey run: error:", "build() raised ValueError", "--pilot remote needs --zenoh-config"
    )


@pytest.mark.subprocess
@pytest.mark.network
def test_a_build_that_opened_a_socket_and_a_serial_port_then_raised_closes_them(tmp_path: Path) -> None:
    """build() made a vehicle with a part holding a listening socket, a pty's serial port and a non-daemon
    thread, then raised: the run command shuts that vehicle's parts down (the part says so), so the process
    exits at once, not by the exit guard (which would add a second line)."""
    port, marker = free_port(), tmp_path / "shut"
    car = write_car(
        tmp_path,
        SERVER_PART
        + """
    def build(argv):
        v = Vehicle()
        v.add(Server(int(argv[0]), argv[1]), outputs=[])
        raise ValueError("the steering servo is not calibrated")
    """,
    )
    out = run_car("run", str(car), "--", str(port), str(marker))
    assert_one_line(out, 2, "build() raised ValueError: the steering servo is not calibrated")
    assert marker.read_text() == "closed: socket -1, serial open False"
    assert_nothing_listens_on(port)


@pytest.mark.subprocess
@pytest.mark.network
def test_a_part_whose_start_raises_is_a_part_failure_and_the_car_exits(tmp_path: Path) -> None:
    """The drive starts and a part's update() raises at once: a part failure (status 1, its one line last),
    every part shut down, the process gone."""
    port, marker = free_port(), tmp_path / "shut"
    car = write_car(
        tmp_path,
        SERVER_PART
        + """
    class Lidar:
        async def update(self):
            raise OSError("no lidar on /dev/ttyUSB0")

        def run_threaded(self):
            return None


    def build(argv):
        v = Vehicle()
        v.add(Server(int(argv[0]), argv[1]), outputs=[])
        v.add(Lidar(), outputs=["lidar/scan"], threaded=True)
        return v
    """,
    )
    out = run_car("run", str(car), "--duration", "10", "--", str(port), str(marker))
    assert out.status == 1, out.err
    assert "Traceback" not in out.err, out.err
    lidar = "part 'Lidar' failed in its background task: OSError: no lidar on /dev/ttyUSB0"
    assert out.lines[-1] == f"asyncdonkey run: error: {lidar}", out.err
    assert marker.read_text() == "closed: socket -1, serial open False"
    assert_nothing_listens_on(port)


@pytest.mark.subprocess
@pytest.mark.network
def test_a_drive_that_refuses_to_start_exits_2_and_shuts_the_parts_down(tmp_path: Path) -> None:
    """Vehicle(safety_process=True) on a car with no actuator the safety process can reach: the drive refuses
    to start, which is a refusal (status 2, one error line), not a crash with a traceback."""
    port, marker = free_port(), tmp_path / "shut"
    car = write_car(
        tmp_path,
        SERVER_PART
        + """
    def build(argv):
        v = Vehicle(safety_process=True)
        v.add(Server(int(argv[0]), argv[1]), outputs=[])
        return v
    """,
    )
    out = run_car("run", str(car), "--", str(port), str(marker))
    assert out.status == 2, out.err
    assert "Traceback" not in out.err, out.err
    errors = [line for line in out.lines if line.startswith("asyncdonkey run: error:")]
    assert errors == out.lines[-1:], out.err  # one error line, the last (the drive's empty report comes before)
    assert "safety_process=True" in errors[0], out.err
    assert marker.read_text() == "closed: socket -1, serial open False"
    assert_nothing_listens_on(port)


@pytest.mark.subprocess
def test_a_thread_build_left_running_cannot_keep_the_refused_car_alive(tmp_path: Path) -> None:
    """The backstop: build() started a non-daemon thread nobody can stop, then raised. The process still exits
    with the refusal's status, EXIT_GRACE_S after its line, naming the thread it did not wait for."""
    car = write_car(
        tmp_path,
        """
    import threading

    def build():
        threading.Thread(target=threading.Event().wait, name="forever").start()
        raise RuntimeError("no camera")
    """,
    )
    out = run_car("run", str(car))
    assert out.status == 2, out.err
    assert "Traceback" not in out.err, out.err
    assert len(out.lines) == 2 and "build() raised RuntimeError: no camera" in out.lines[0], out.err
    assert out.lines[1] == "asyncdonkey: exiting without waiting for threads still running: forever"
    assert out.seconds >= EXIT_GRACE_S


@pytest.mark.subprocess
def test_the_car_options_help_exits_0_and_a_bad_car_option_2(tmp_path: Path) -> None:
    """The car's own option parser ends build() with SystemExit: its status is the command's."""
    assert run_car("run", CAR, "--", "--help").status == 0
    out = run_car("run", CAR, "--", "--laps", "many")
    assert out.status == 2 and "--laps" in out.err and "Traceback" not in out.err, out.err
