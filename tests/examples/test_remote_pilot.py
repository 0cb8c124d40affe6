"""The off-board pilot end to end: examples/car.py and examples/remote_pilot.py in two processes on loopback.

The car publishes its frames and takes ``pilot/*`` from the network; the pilot process runs the ONNX model on
those frames. The test watches the car's published throttle and speed from a third session, lets the remote
pilot drive, then kills the pilot process (SIGKILL, as a crash or a lost laptop would) and checks that the
car's throttle goes to neutral within the failsafe window. Bounded: every wait has a deadline, and both
processes are killed at the end whatever happens.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh
from example_loader import load_example

from asyncdonkey.parts.zenoh import zenoh_config

ROOT = Path(__file__).resolve().parents[2]
FAILSAFE_S = 0.25


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "asyncdonkey.cli", "run", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )


class Watch:
    """(monotonic time, value) series of some of the car's keys, from a session of the test's own."""

    def __init__(self, port: int) -> None:
        cfg = zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
        cfg.insert_json5("connect/exit_on_failure", "false")
        cfg.insert_json5("listen/endpoints", "[]")
        self.session = zenoh.open(cfg)
        self.lock = threading.Lock()
        self.series: dict[str, list[tuple[float, object]]] = {}
        self.subs = [
            self.session.declare_subscriber(f"cars/sim/{k}", self._on) for k in ("sim/throttle", "sim/speed", "status")
        ]

    def _on(self, sample) -> None:
        t = time.monotonic()
        key = str(sample.key_expr).removeprefix("cars/sim/")
        value = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.series.setdefault(key, []).append((t, value))

    def get(self, key: str) -> list[tuple[float, object]]:
        with self.lock:
            return list(self.series.get(key, []))

    def close(self) -> None:
        self.session.close()


def _wait(cond, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def test_car_drives_on_a_remote_pilot_and_stops_when_the_pilot_dies():
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    car = _spawn("examples/car.py", "--", "--pilot", "remote", "--zenoh-listen", endpoint, "--seconds", "40")
    pilot = None
    watch = None
    try:
        watch = Watch(port)
        pilot = _spawn("examples/remote_pilot.py", "--", "--zenoh-connect", endpoint)
        # the remote pilot's commands open the throttle
        assert _wait(lambda: any(v > 0 for _, v in watch.get("sim/throttle")), 30), "the remote pilot never drove"
        t_drive = time.monotonic()
        time.sleep(2.0)
        speeds = [v for t, v in watch.get("sim/speed") if t > t_drive + 1.0]
        assert speeds and min(speeds) > 0.3  # driving, not creeping
        status = watch.get("status")[-1][1]
        assert status["mode"] == "local" and status["ages_ms"]["pilot/throttle"] < 200
        # the pilot dies
        pilot.send_signal(signal.SIGKILL)
        t_kill = time.monotonic()
        pilot.wait(timeout=10)
        time.sleep(1.0)
        after = [(t - t_kill, v) for t, v in watch.get("sim/throttle") if t > t_kill]
        # the command's age passes 250 ms at the latest 250 ms after the kill; the next tick (50 ms) stops the car;
        # 150 ms more for a late tick on a loaded machine and the delivery to this session
        first_zero = next(t for t, v in after if v == 0.0)
        assert first_zero < FAILSAFE_S + 0.05 + 0.15, after[:12]
        assert all(v == 0.0 for t, v in after if t >= first_zero)
        assert all(v > 0 for t, v in after if t < first_zero - 0.06)  # it was driving until then
    finally:
        for proc in (pilot, car):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        if watch is not None:
            watch.close()
        outputs = []
        for proc in (pilot, car):
            if proc is None:
                continue
            try:
                out, _ = proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, _ = proc.communicate()
            outputs.append(out)
    car_out = outputs[-1]
    assert "StaleCommandStop: throttle command is" in car_out
    assert "off track 0 ticks" in car_out


def test_the_car_refuses_a_remote_pilot_on_zenohs_open_defaults():
    car_py = load_example("car")
    with pytest.raises(ValueError, match="anyone on the network steer the car"):
        car_py.build(["--pilot", "remote"])
