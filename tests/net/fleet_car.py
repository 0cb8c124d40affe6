"""A light car for fleet tests and benchmarks, run as a process of its own: recorded frames out, pilot commands in.

    python tests/net/fleet_car.py --frames frames.npy --car car1 --car car2 --connect tcp/127.0.0.1:7447
    python tests/net/fleet_car.py --frames frames.npy --car car1 --config pair/{car}/car.json5

Each ``--car`` is a :class:`asyncdonkey.Vehicle` with its own Zenoh session (as a car on its own machine), at
``--hz`` (the cars of one process start spread over one period: out of phase, as separate cars are): a player
of the recorded frames on ``cam/image_array``, the :class:`ZenohPublisher` that sends them (raw, or JPEG with
``--jpeg``), the :class:`ZenohSubscriber` of the one-sample command
(``cars/<car>/pilot/command``, as ``examples/car.py --pilot remote`` takes it), and a
:class:`~asyncdonkey.parts.failsafe.StaleCommandStop` of ``--failsafe-ms`` writing the throttle the car would
drive (``car/throttle``). Nothing else: a car whose process costs little, so many fit on one machine.

It prints JSON lines on stdout: ``{"event": "driving", "car", "t"}`` at each car's first command, and when it
stops (``--seconds``, SIGINT or SIGTERM) one ``{"event": "report", ...}`` per car: frames sent, commands taken,
each command's arrival time and frame-to-command latency (arrival minus the origin of the frame it answers,
which the server carries back), and every change of the throttle the car ends with (``[time, value]``, the
monotonic clock, which all processes of the machine share). Imports nothing relative (it runs as a script).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from asyncdonkey import Vehicle
from asyncdonkey.parts.failsafe import StaleCommandStop
from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber, zenoh_config

CMD = ["pilot/angle", "pilot/throttle"]


class FramePlayer:
    """``cam/image_array``: the recorded frames in turn, one per tick (a new array object each time)."""

    def __init__(self, frames: np.ndarray) -> None:
        self.frames = frames
        self.k = 0

    def run(self) -> np.ndarray:
        frame = self.frames[self.k % len(self.frames)].copy()
        self.k += 1
        return frame


class ThrottleLog:
    """Every change of the throttle the car ends with: ``[time, value]`` (``None`` before any command)."""

    def __init__(self) -> None:
        self.changes: list[tuple[float, Any]] = []
        self.last: Any = "unset"

    def run(self, throttle: Any) -> None:
        if throttle != self.last:
            self.changes.append((time.monotonic(), throttle))
            self.last = throttle


class FleetCar:
    """One light car (module docstring)."""

    def __init__(self, name: str, config: Any, frames: np.ndarray, jpeg: int | None, failsafe_s: float) -> None:
        self.name = name
        self.link = ZenohLink(f"cars/{name}", config)
        self.vehicle = v = Vehicle()
        v.add(FramePlayer(frames), outputs=["cam/image_array"])
        self.camera = ZenohPublisher(self.link, ["cam/image_array"], jpeg={"cam/image_array": jpeg} if jpeg else None)
        v.add(self.camera, inputs=self.camera.inputs)
        self.commands = ZenohSubscriber(self.link, CMD, group=PILOT_COMMAND)
        v.add(self.commands, outputs=CMD)
        v.add(StaleCommandStop(failsafe_s), inputs=["pilot/throttle", "pilot/throttle@age"], outputs=["car/throttle"])
        self.log = ThrottleLog()
        v.add(self.log, inputs=["car/throttle"])
        self.arrivals: list[float] = []
        self.latency: list[float] = []
        self.first: float | None = None
        self._lock = threading.Lock()
        self.commands.subscribe(self._on_command)

    def _on_command(self, value: Any, origin: float) -> None:
        now = self.link.now()
        with self._lock:
            self.arrivals.append(time.monotonic())
            self.latency.append(now - origin)
            if self.first is None:
                self.first = time.monotonic()
                print(json.dumps({"event": "driving", "car": self.name, "t": self.first}), flush=True)

    def report(self) -> dict[str, Any]:
        with self._lock:
            lat = np.array(self.latency) * 1e3
            return {
                "event": "report",
                "car": self.name,
                "frames_sent": self.camera.sent,
                "frame_bytes": self.camera.bytes_sent,
                "commands": len(self.arrivals),
                "arrivals": self.arrivals,
                "latency_ms": lat.round(3).tolist(),
                "latency_p50_ms": float(np.percentile(lat, 50)) if len(lat) else None,
                "latency_p99_ms": float(np.percentile(lat, 99)) if len(lat) else None,
                "throttle_changes": [[t, v] for t, v in self.log.changes],
                "counters": self.commands.counters(),
            }


async def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="light fleet cars: recorded frames out, pilot commands in")
    ap.add_argument("--frames", required=True, help=".npy of uint8 frames (N, 120, 160, 3)")
    ap.add_argument("--car", action="append", required=True, help="a car's name (repeatable: several cars)")
    ap.add_argument("--connect", help="endpoint of the server, plain TCP on a bench (e.g. tcp/127.0.0.1:7447)")
    ap.add_argument("--config", help="a Zenoh config file per car, {car} standing for its name")
    ap.add_argument("--hz", type=float, default=20.0, help="frames per second per car (default 20)")
    ap.add_argument("--jpeg", type=int, help="send frames as JPEG of this quality")
    ap.add_argument("--failsafe-ms", type=float, default=250.0, help="the stale-command stop (default 250)")
    ap.add_argument("--seconds", type=float, default=0.0, help="stop after S seconds (0: at SIGINT/SIGTERM)")
    args = ap.parse_args(argv)
    frames = np.load(args.frames)
    cars = []
    for name in args.car:
        if args.config:
            config = zenoh_config(args.config.format(car=name))
        else:
            config = zenoh_config(mode="client", connect=[args.connect], extra={"connect/exit_on_failure": False})
            config.insert_json5("listen/endpoints", "[]")
        cars.append(FleetCar(name, config, frames, args.jpeg, args.failsafe_ms / 1e3))
    loop = asyncio.get_running_loop()

    def stop() -> None:
        for car in cars:
            car.vehicle.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop)
    duration = args.seconds if args.seconds > 0 else None
    print(json.dumps({"event": "started", "cars": args.car, "t": time.monotonic()}), flush=True)

    async def drive(k: int, car: FleetCar) -> None:
        # cars of one process start spread over a period, as cars on their own machines are out of phase
        await asyncio.sleep(k / len(cars) / args.hz)
        await car.vehicle.run(rate_hz=args.hz, duration=duration)

    await asyncio.gather(*(drive(k, car) for k, car in enumerate(cars)))
    for car in cars:
        print(json.dumps(car.report()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))


def record_sim_frames(path: str, count: int = 40, dt: float = 0.05) -> np.ndarray:
    """Render ``count`` frames of the simulator's track, driven by its scripted driver at ``1/dt`` Hz, and save
    them to ``path`` (.npy): frames a real pilot steers on, recorded once for every car to replay."""
    from asyncdonkey.parts.sim import ScriptedDriver, Simulator

    sim = Simulator()
    driver = ScriptedDriver(sim.track, seed=0, rate_hz=1 / dt)
    frames = []
    tel = sim.step(0.0, 0.0, 0.0)
    for _ in range(count):
        angle, throttle = driver.run(tel.x, tel.y, tel.heading)
        tel = sim.step(dt, angle, throttle)
        frames.append(sim.render())
    out = np.stack(frames).astype(np.uint8)
    np.save(path, out)
    return out


class FleetProcess:
    """A process of a fleet (a car of this script, a pilot server) whose stdout JSON lines are collected as they
    come, its other lines kept: what the fleet tests and ``benchmarks/fleet.py`` read from the processes they start.
    """

    def __init__(self, args: list[str], cwd: str | os.PathLike[str] | None = None) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.p = subprocess.Popen(
            [sys.executable, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
        )
        self.lines: list[str] = []
        self.events: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.lines.append(line)
            if line.startswith("{"):
                try:
                    self.events.append(json.loads(line))
                except ValueError:
                    pass

    def of(self, kind: str) -> list[dict[str, Any]]:
        """The events of one kind so far (``{"event": kind, ...}``)."""
        return [e for e in list(self.events) if e.get("event") == kind]

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> None:
        """``sig``, then a kill if it has not ended within ``timeout``; its output read to the end."""
        if self.p.poll() is None:
            self.p.send_signal(sig)
        try:
            self.p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait()
        self._reader.join(timeout=5)


#: This script, for the processes that run it.
SCRIPT = Path(__file__).resolve()
