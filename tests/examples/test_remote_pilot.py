"""The off-board pilot end to end: examples/car.py and examples/remote_pilot.py in two processes on loopback.

The car publishes its frames and takes ``pilot/*`` from the network; the pilot process runs the ONNX model on
those frames. The test watches the car's published throttle and speed from a third session, lets the remote
pilot drive, then kills the pilot process (SIGKILL, as a crash or a lost laptop would) and checks that the
car's throttle goes to neutral within the failsafe window. Bounded: every wait has a deadline, and both
processes are killed at the end whatever happens.
"""

import json
import math
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

from asyncdonkey.parts.zenoh import zenoh_config

from ..waiting import wait_until
from .example_loader import load_example

ROOT = Path(__file__).resolve().parents[2]
FAILSAFE_S = 0.25


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "asyncdonkey.commands", "run", *args],
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


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.subprocess
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
        wait_until(lambda: any(v > 0 for _, v in watch.get("sim/throttle")), 30, "the remote pilot to drive")
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


class _BadPilot:
    """From a session of the test's own: a good command (straight, throttle 0.5) and a bad one every 20 ms for
    ``good_s``, then only bad ones, each fresh and correctly numbered, on the car's ``pilot/command`` key."""

    BAD = [
        ('{"pilot/angle": 0.0, "pilot/throttle": Infinity}', "application/json;group;v=1"),
        ('{"pilot/angle": NaN, "pilot/throttle": 0.5}', "application/json;group;v=1"),
        ('{"pilot/angle": 0.0, "pilot/throttle": "full"}', "application/json;group;v=1"),
        ('{"pilot/angle": [1], "pilot/throttle": 0.5}', "application/json;group;v=1"),
        ('{"pilot/angle": 0.0, "pilot/throttle": ' + "9" * 400 + "}", "application/json;group;v=1"),
        ('{"pilot/angle": 0.0, "pilot/throttle": 0.66}', "text/plain"),
        ("", "application/json;group;v=1"),
        (None, "delete"),
    ]

    def __init__(self, port: int, good_s: float) -> None:
        cfg = zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
        cfg.insert_json5("listen/endpoints", "[]")
        self.session = zenoh.open(cfg)
        self.key = "cars/sim/pilot/command"
        self.good_s = good_s
        self.seq = 0
        self.last_good: float | None = None

    def _send(self, payload: str | None, encoding: str) -> None:
        from asyncdonkey.parts.zenoh.codec import pack_attachment

        self.seq += 1
        att = pack_attachment(0.0, self.seq, 1)
        block = zenoh.CongestionControl.BLOCK
        if encoding == "delete":
            self.session.delete(self.key, attachment=att, congestion_control=block)
        else:
            self.session.put(self.key, payload.encode(), encoding=encoding, attachment=att, congestion_control=block)

    async def update(self) -> None:
        import asyncio

        t0 = time.monotonic()
        for k in range(10_000):
            if time.monotonic() - t0 < self.good_s:
                self._send('{"pilot/angle": 0.0, "pilot/throttle": 0.5}', "application/json;group;v=1")
                self.last_good = time.monotonic()
            self._send(*self.BAD[k % len(self.BAD)])
            await asyncio.sleep(0.02)

    def run(self) -> None:
        pass


class _Commands:
    """Each tick: the time and what the drive mode and the stale-command stop put out."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, object, object, object]] = []

    def run(self, angle, throttle, sim_throttle) -> None:
        self.rows.append((time.monotonic(), angle, throttle, sim_throttle))


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_bad_remote_commands_neither_stop_nor_steer_the_simulated_car():
    """The car of ``examples/car.py --pilot remote`` on loopback: bad commands between good ones are refused
    (the car drives on), and once only bad ones come the last good command ages out and the car stops."""
    from asyncdonkey.parts.zenoh import ZenohSubscriber

    car_py = load_example("car")
    port = _free_port()
    listen = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    v, _ = car_py.make_car(pilot="remote", zenoh=listen, seconds=0, status=None)
    bad = _BadPilot(port, good_s=0.8)
    seen = _Commands()
    v.add(bad)
    v.add(seen, inputs=["angle", "throttle", "sim/throttle"])
    sub = next(e.part for e in v.parts if isinstance(e.part, ZenohSubscriber))
    try:
        await v.run(rate_hz=20, max_loop_count=30)  # 1.5 s: never raised into (the drive ends by itself)
    finally:
        bad.session.close()
    t0 = seen.rows[0][0]
    commands = [r for r in seen.rows if r[2] is not None]
    assert commands and all(isinstance(x, float) and math.isfinite(x) for r in commands for x in r[1:])
    driving = [r[3] for r in seen.rows if 0.35 < r[0] - t0 < 0.75]
    assert driving and all(x == pytest.approx(0.65) for x in driving)  # 0.5 x the sim's ai_throttle_mult 1.3
    assert {r[1] for r in commands} == {0.0}  # never steered by a bad half
    stopped = [r[3] for r in seen.rows if r[0] > bad.last_good + FAILSAFE_S + 0.05 + 0.05]
    assert stopped and set(stopped) == {0.0}
    refused = sub.refused
    assert refused["pilot/throttle"].keys() == {"inf", "type", "range"}
    assert refused["pilot/angle"].keys() == {"nan", "type"}
    assert refused["pilot/command"].keys() == {"encoding", "empty"}
    assert sub.counters()["lost"] == 0
