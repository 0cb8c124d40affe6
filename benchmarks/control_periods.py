"""Control periods of a Donkeycar-style car: in order, pipelined, and started by the frame.

    python benchmarks/control_periods.py            # the virtual-clock tables and the real-loop run (about 30 s)
    python benchmarks/control_periods.py --quick    # shorter
    python benchmarks/control_periods.py --json     # for run_all.py

**The seed's car on the virtual clock.** Each part costs the time the Donkeycar control-period analysis gives
it on a Raspberry Pi 4: camera read 2 ms, controller 1 ms, pilot inference 20 / 40 / 80 ms, actuator write
1 ms, tub write 5 ms, at ``DRIVE_LOOP_HZ = 20``. A cost is an ``await asyncio.sleep(cost)`` inside the part, so
on the virtual clock the figures are exact and the same every run. Two drives: data collection (the driver
drives, the tub records, no inference) and autopilot (the pilot drives). Three ways to run the pilot:

* ``in order``: inside the tick, as Donkeycar does (its tick waits for the inference);
* ``pipelined``: ``add(pilot, pipelined=True)``: beside the ticks, started at each tick with the newest frame;
* ``pipelined + react``: the same, with the drive mode and the actuator added with ``react=True``: they also run
  the moment the pilot publishes, instead of at the next tick;
* ``frame-started``: ``pipelined=True, trigger="cam/image_array"`` with a camera that captures on its own
  20 fps schedule and pushes each frame, the drive mode and actuator with ``react=True``.

Printed for each: loop rate, pilot output rate, overruns, and sensing-to-actuation latency p50/p99 (the time the
actuator took the command minus the capture time of the frame behind it, once per command).

**The same car on the real loop** (uvloop, real time), with ``OnnxPilot`` running a Donkeycar-shaped CNN widened
to take about 40 ms here (``export_donkey_linear_shaped(width=...)``), in order and pipelined.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from asyncdonkey import Vehicle, get_clock
from asyncdonkey.latest import Latest
from asyncdonkey.loop import run_blocking
from asyncdonkey.parts.control import DriveMode, PilotCondition
from asyncdonkey.testing import VirtualClockLoop
from machine_info import describe

RATE = 20
COST = {"camera": 0.002, "controller": 0.001, "actuator": 0.001, "tub": 0.005}
MODES = ("in order", "pipelined", "pipelined + react", "frame-started")


class Costly:
    """A part whose run() takes ``cost`` seconds of (virtual) time and returns ``value``."""

    def __init__(self, cost: float, value: Any = None) -> None:
        self.cost = cost
        self.value = value

    async def run(self, *args: Any) -> Any:
        await asyncio.sleep(self.cost)
        return self.value() if callable(self.value) else self.value


class Camera:
    """A 2 ms camera read in the tick (``push=False``), or a camera capturing on its own 20 fps schedule
    that pushes each frame (``push=True``, for the frame-started mode)."""

    def __init__(self, push: bool) -> None:
        self.push = push
        self.frames: Latest[int] = Latest()
        self.n = 0
        if push:
            self.update = self._capture  # an async update() task only when it captures by itself

    async def run(self) -> int | None:
        if self.push:
            s = self.frames.sample
            return None if s is None else s.value
        await asyncio.sleep(COST["camera"])
        self.n += 1
        return self.n

    def output_origin(self) -> float | None:
        if not self.push:
            return None  # read in the tick: sensed when run() returns
        s = self.frames.sample
        return None if s is None else s.timestamp

    def subscribe(self, callback: Any) -> Any:
        return self.frames.subscribe(callback)

    async def _capture(self) -> None:
        clock = get_clock()
        t0 = clock.now() + 0.013  # not in phase with the ticks, as a real camera is not
        k = 0
        while True:
            await clock.sleep_until(t0 + k / RATE)
            await asyncio.sleep(COST["camera"])
            self.n += 1
            self.frames.publish(self.n, clock.now())
            k += 1


class Actuator:
    """The ESC/servo write (1 ms); its latency is measured by the drive (actuator=True)."""

    async def run(self, angle: Any, throttle: Any) -> None:
        await asyncio.sleep(COST["actuator"])


def seed_car(inference_s: float, mode: str, autopilot: bool) -> Vehicle:
    v = Vehicle()
    cam = Camera(push=mode == "frame-started")
    v.add(cam, outputs=["cam/image_array"])
    v.add(
        Costly(COST["controller"], ("local" if autopilot else "user", 0.0, 0.5)),
        outputs=["user/mode", "user/angle", "user/throttle"],
        name="controller",
    )
    if autopilot:
        v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
        v.add(
            # values unlike the driver's: equal float constants in one module are one object, and a value that
            # is the very object of two inputs counts as the older one's (docs/provenance.md)
            Costly(inference_s, lambda: (0.05, 0.45)),
            inputs=["cam/image_array"],
            outputs=["pilot/angle", "pilot/throttle"],
            run_condition="run_pilot",
            pipelined=mode != "in order",
            trigger="cam/image_array" if mode == "frame-started" else None,
            name="pilot",
        )
    react = mode in ("pipelined + react", "frame-started")
    v.add(
        DriveMode(),
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
        outputs=["angle", "throttle"],
        react=react,
    )
    v.add(Actuator(), inputs=["angle", "throttle"], actuator=True, react=react, name="actuator")
    v.add(Costly(COST["tub"]), inputs=["cam/image_array", "angle", "throttle"], name="tub")
    return v


def _latency(report: Any) -> tuple[float | None, float | None]:
    lat = report.latency_ms.get("actuator") or {}
    return lat.get("50%"), lat.get("99%")


def virtual_table(seconds: float) -> list[dict[str, Any]]:
    rows = []
    ticks = int(seconds * RATE)
    for autopilot, inference in ((False, 0.0), (True, 0.02), (True, 0.04), (True, 0.08)):
        for mode in MODES if autopilot else ("in order",):
            v = seed_car(inference, mode, autopilot)
            with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
                report = runner.run(v.run(RATE, ticks))
            pilot = report.pipelined.get("pilot")
            if pilot is not None:
                pilot_hz = pilot["rate_hz"]
            elif autopilot:
                pilot_hz = report.achieved_hz
            else:
                pilot_hz = None
            p50, p99 = _latency(report)
            rows.append(
                {
                    "drive": "autopilot" if autopilot else "data collection",
                    "inference_ms": inference * 1e3,
                    "mode": mode,
                    "loop_hz": report.achieved_hz,
                    "pilot_hz": pilot_hz,
                    "overruns": report.overruns,
                    "ticks": report.loops,
                    "latency_p50_ms": p50,
                    "latency_p99_ms": p99,
                }
            )
    return rows


def real_loop(seconds: float, target_ms: float = 40.0) -> dict[str, Any]:
    """The seed car on the real loop with a real ONNX model sized to cost about ``target_ms`` here."""
    from asyncdonkey.parts.pilot import OnnxPilot
    from asyncdonkey.pilot_export import export_donkey_linear_shaped

    tmp = Path(tempfile.mkdtemp())
    width, model, took = 4.0, None, 0.0
    for _ in range(6):  # widen the CNN until one inference takes about the target
        model = export_donkey_linear_shaped(tmp / f"w{width:g}.onnx", width=width)
        pilot = OnnxPilot(model)
        frame = np.zeros((120, 160, 3), np.uint8)
        pilot.predict(frame)
        times = []
        for _ in range(5):
            t = time.perf_counter()
            pilot.predict(frame)
            times.append(time.perf_counter() - t)
        took = float(np.median(times)) * 1e3
        if abs(took - target_ms) < 0.2 * target_ms:
            break
        width *= (target_ms / took) ** 0.5
    out: dict[str, Any] = {"model_width": round(width, 2), "inference_p50_ms": took, "modes": {}}
    for mode in ("in order", "pipelined"):

        class Frames:
            def __init__(self) -> None:
                self.frame = np.zeros((120, 160, 3), np.uint8)

            def run(self) -> np.ndarray:
                return self.frame

        v = Vehicle()
        v.add(Frames(), outputs=["cam/image_array"])
        v.add(
            OnnxPilot(model),
            inputs=["cam/image_array"],
            outputs=["pilot/angle", "pilot/throttle"],
            pipelined=mode == "pipelined",
            name="pilot",
        )
        v.add(Actuator(), inputs=["pilot/angle", "pilot/throttle"], actuator=True, name="actuator")
        report = run_blocking(v.run(RATE, int(seconds * RATE)))
        pilot_stats = report.pipelined.get("pilot")
        p50, p99 = _latency(report)
        out["modes"][mode] = {
            "loop_hz": report.achieved_hz,
            "pilot_hz": pilot_stats["rate_hz"] if pilot_stats else report.achieved_hz,
            "overruns": report.overruns,
            "latency_p50_ms": p50,
            "latency_p99_ms": p99,
        }
    return out


def _f(x: Any, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    results = {
        "machine": describe(),
        "virtual": virtual_table(10.0 if args.quick else 60.0),
        "real": real_loop(3.0 if args.quick else 10.0),
    }
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print("The seed's car on the virtual clock (20 Hz; camera 2, controller 1, actuator 1, tub 5 ms):")
    head = f"{'drive':16} {'inference':>9} {'mode':18} {'loop Hz':>8} {'pilot Hz':>8} {'overruns':>8}"
    print(f"{head} {'latency p50/p99 ms':>19}")
    for r in results["virtual"]:
        print(
            f"{r['drive']:16} {_f(r['inference_ms'], 0) + ' ms':>9} {r['mode']:18} {r['loop_hz']:8.2f} "
            f"{_f(r['pilot_hz'], 2):>8} {r['overruns']:8d} {_f(r['latency_p50_ms']):>9} / {_f(r['latency_p99_ms']):<8}"
        )
    real = results["real"]
    print(
        f"\nOn the real loop ({results['machine']}), OnnxPilot on a CNN of width {real['model_width']} "
        f"({real['inference_p50_ms']:.1f} ms per inference):"
    )
    for mode, r in real["modes"].items():
        print(
            f"  {mode:10} loop {r['loop_hz']:6.2f} Hz, pilot {r['pilot_hz']:6.2f} Hz, overruns {r['overruns']}, "
            f"latency p50 {_f(r['latency_p50_ms'])} ms, p99 {_f(r['latency_p99_ms'])} ms"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
