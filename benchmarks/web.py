"""Web controller cost: command latency and what video viewers cost the car, beside Donkeycar's.

Both controllers run as a part of the same asyncdonkey drive loop (20 Hz, uvloop), fed by the same camera (a new
160x120 frame every tick, 20 fps), so the difference is the web controller alone:

* ours: :class:`~asyncdonkey.parts.web.WebController` (aiohttp on the loop; one JPEG per new frame, shared);
* Donkeycar 5.3's ``LocalWebController`` (tornado in its own thread, as a threaded part; its ``/video``
  encodes a JPEG every 5 ms for each viewer).

Figures:

* **command latency**: a WebSocket client (its own thread and event loop) sends ``{"angle": a, "throttle": 0}``
  every 37 ms with a fresh ``a``; a part after the controller records when ``user/angle`` becomes ``a`` in
  Memory. p50 / p99 in ms. A command waits for the next tick (50 ms period), so the p50 is about half a period
  for both: what differs is the tail. Behind the controller, ``DriveMode`` and a ``PWMThrottle`` (on a simulated
  PCA9685) with ``throttle@age``, as on a car; for ours the drive's profiler also gives **command arrival to PWM
  write** (the throttle's sensing-to-actuation latency, whose origin is the command's arrival). Donkeycar's
  controller does not say when its commands arrived, so there is no such figure for it.
* **CPU** of the car's process (all its threads; the viewers run in another process), in % of one core, and
  **tick lateness** p99 (the loop's own profiler), with 0, 1 and 3 viewers of ``/video`` reading as fast as
  they can, plus the frames each viewer received per second.

Every configuration runs in several rounds, interleaved; CPU, lateness and frame rate are the medians of the
rounds' figures, the command latencies percentiles of all the rounds' commands.

    python benchmarks/web.py            # 3 rounds of 5 s per configuration (about 2.5 min with Donkeycar)
    python benchmarks/web.py --quick    # one round of 2 s per configuration
    python benchmarks/web.py --json     # figures as JSON for benchmarks/run_all.py
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import logging
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking
from asyncdonkey.parts.actuators import PWMThrottle
from asyncdonkey.parts.control import DriveMode
from asyncdonkey.parts.web import WEB_INPUTS, WEB_OUTPUTS, WebController
from machine_info import describe

try:  # Donkeycar prints a banner on import; keep it out of the figures
    with contextlib.redirect_stdout(io.StringIO()):
        from donkeycar.parts.web_controller.web import LocalWebController
except ImportError:  # pragma: no cover - donkeycar (with tornado and requests) is optional
    LocalWebController = None

RATE_HZ = 20
VIEWERS = (0, 1, 3)
SEND_EVERY_S = 0.037
BOUNDARY = b"--boundarydonotcross"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Camera:
    """A new frame object every tick (20 fps at 20 Hz), cycling through textured road-like images."""

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        yy, xx = np.mgrid[0:120, 0:160]
        self.frames = []
        for k in range(20):
            road = np.abs(xx - 80 - 20 * np.sin(k / 5 + yy / 40)) < (yy - 30).clip(0) * 0.9
            img = np.where(road[..., None], 90, 60).astype(np.float32) + rng.normal(0, 6, (120, 160, 3))
            self.frames.append(img.clip(0, 255).astype(np.uint8))
        self.k = 0

    def run(self) -> np.ndarray:
        self.k += 1
        return self.frames[self.k % len(self.frames)].copy()  # a new array, as a camera hands out


class Probe:
    """Records how long after it was sent each command's angle reached Memory."""

    def __init__(self) -> None:
        self.sent: dict[float, float] = {}
        self.latency: list[float] = []
        self.last: Any = None

    def run(self, angle: Any) -> None:
        if angle != self.last:
            self.last = angle
            t = self.sent.get(angle)
            if t is not None:
                self.latency.append(time.monotonic() - t)


if LocalWebController is not None:

    class DonkeyController(LocalWebController):  # type: ignore[misc, valid-type]
        """Donkeycar's controller with a shutdown that stops its tornado loop (its own does nothing)."""

        def shutdown(self) -> None:
            if self.loop is not None:
                self.loop.add_callback(self.loop.stop)


def sender(port: int, headers: dict[str, str], probe: Probe, stop: threading.Event) -> None:
    """The phone: a WebSocket client sending a fresh angle every ``SEND_EVERY_S`` in its own thread."""
    import aiohttp

    async def main() -> None:
        async with (
            aiohttp.ClientSession(headers=headers) as http,
            http.ws_connect(f"http://127.0.0.1:{port}/wsDrive") as ws,
        ):
            k = 0
            while not stop.is_set():
                k += 1
                angle = round((k % 997 + 1) / 1000, 6)
                probe.sent[angle] = time.monotonic()
                await ws.send_str(json.dumps({"angle": angle, "throttle": 0.0}))
                await asyncio.sleep(SEND_EVERY_S)

    asyncio.run(main())


async def wait_port(port: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            _, w = await asyncio.open_connection("127.0.0.1", port)
            w.close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)


async def drive(kind: str, viewers: int, seconds: float) -> dict[str, Any]:
    port = free_port()
    v = Vehicle()
    v.add(Camera(), outputs=["cam/image_array"], name="camera")
    headers: dict[str, str] = {}
    if kind == "ours":
        ctr = WebController(port, host="127.0.0.1", announce=None)
        v.add(ctr, inputs=list(WEB_INPUTS), outputs=list(WEB_OUTPUTS), name="web")
    else:
        ctr = DonkeyController(port=port)
        v.add(ctr, inputs=list(WEB_INPUTS), outputs=list(WEB_OUTPUTS), threaded=True, name="web")
    probe = Probe()
    v.add(probe, inputs=["user/angle"], name="probe")
    from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

    i2c = I2CSimulator()
    i2c.attach(PCA9685Model(), address=0x40, bus=1)
    buses = i2c.registry(retry_delay_s=0)
    v.add(
        DriveMode(),
        inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
        outputs=["angle", "throttle"],
    )
    v.add(PWMThrottle("PCA9685.1:40.0", buses=buses, arm_s=0.1), inputs=["throttle", "throttle@age"], name="throttle")
    task = asyncio.create_task(v.run(rate_hz=RATE_HZ))
    stop = threading.Event()
    client: threading.Thread | None = None
    try:
        await wait_port(port)
        if kind == "ours":
            headers = {"Authorization": f"Token {ctr.token}"}
        await asyncio.sleep(1.0)  # warm up
        proc = None
        if viewers:
            proc = await asyncio.create_subprocess_exec(
                sys.executable,
                str(Path(__file__).resolve()),
                "--viewer-process",
                json.dumps({"port": port, "n": viewers, "seconds": seconds + 1.0, "headers": headers}),
                stdout=subprocess.PIPE,
            )
            await asyncio.sleep(0.5)  # the viewers connect
        client = threading.Thread(target=sender, args=(port, headers, probe, stop), daemon=True)
        client.start()
        await asyncio.sleep(0.3)
        n0 = v.profiler.lateness.count
        pwm = v.profiler.latency_for("throttle")
        p0 = pwm.count
        probe.latency.clear()
        cpu0, t0 = time.process_time(), time.monotonic()
        await asyncio.sleep(seconds)
        cpu, wall = time.process_time() - cpu0, time.monotonic() - t0
        n1 = v.profiler.lateness.count
        late = v.profiler.lateness.recent(drop_last=False)[-(n1 - n0) :]
        p1 = pwm.count
        to_pwm = pwm.recent(drop_last=False)[-(p1 - p0) :] if p1 > p0 else np.array([])
        lat = np.array(probe.latency)
        stop.set()
        frames_per_s = 0.0
        if proc is not None:
            out, _ = await proc.communicate()
            got = json.loads(out)
            frames_per_s = float(np.mean(got["fps"]))
    finally:
        stop.set()
        v.stop()
        await task
        if client is not None:
            client.join(5)
        buses.close_all()
    return {
        "cpu_pct": 100.0 * cpu / wall,
        "late": late,
        "latency": lat,
        "to_pwm": to_pwm if kind == "ours" else np.array([]),
        "fps": frames_per_s,
    }


def _pct_ms(samples: np.ndarray, q: float) -> float | None:
    return float(np.percentile(samples, q)) * 1e3 if len(samples) else None


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One configuration over its rounds: medians of the per-round CPU, lateness p99 and frame rate (one
    disturbed round on a shared machine does not make the figure), percentiles of the pooled command samples."""
    lat = np.concatenate([r["latency"] for r in runs])
    to_pwm = np.concatenate([r["to_pwm"] for r in runs])
    return {
        "rounds": len(runs),
        "cpu_pct": float(np.median([r["cpu_pct"] for r in runs])),
        "lateness_p99_ms": float(np.median([np.percentile(r["late"], 99) for r in runs])) * 1e3,
        "lateness_p99_ms_rounds": [float(np.percentile(r["late"], 99)) * 1e3 for r in runs],
        "latency_p50_ms": _pct_ms(lat, 50),
        "latency_p99_ms": _pct_ms(lat, 99),
        "commands": len(lat),
        "to_pwm_p50_ms": _pct_ms(to_pwm, 50),
        "to_pwm_p99_ms": _pct_ms(to_pwm, 99),
        "frames_per_s_per_viewer": float(np.median([r["fps"] for r in runs])),
    }


def viewer_process(spec: dict[str, Any]) -> None:
    """``n`` viewers of ``/video`` reading as fast as they can for ``seconds``; prints the parts they got."""

    async def one(stop_at: float) -> tuple[int, int, float]:
        r, w = await asyncio.open_connection("127.0.0.1", spec["port"])
        head = "".join(f"{k}: {v}\r\n" for k, v in spec["headers"].items())
        w.write(f"GET /video HTTP/1.1\r\nHost: 127.0.0.1\r\n{head}\r\n".encode())
        parts = nbytes = 0
        first = last = 0.0
        tail = b""
        while time.monotonic() < stop_at:
            try:
                chunk = await asyncio.wait_for(r.read(65536), 0.5)
            except TimeoutError:
                continue
            if not chunk:
                break
            nbytes += len(chunk)
            data = tail + chunk
            n = data.count(BOUNDARY + b"\n")  # a part's boundary line (the header's "boundary=" ends in \r\n)
            if n:
                last = time.monotonic()
                if not parts:
                    first = last
                parts += n
            tail = data[-len(BOUNDARY) :]  # a boundary line split across reads counts once
        w.close()
        return parts, nbytes, (parts - 1) / (last - first) if parts > 1 and last > first else 0.0

    async def main() -> dict[str, Any]:
        t0 = time.monotonic()
        got = await asyncio.gather(*(one(t0 + spec["seconds"]) for _ in range(spec["n"])))
        return {
            "parts": sum(g[0] for g in got),
            "bytes": sum(g[1] for g in got),
            "fps": [g[2] for g in got],
            "seconds": time.monotonic() - t0,
        }

    print(json.dumps(asyncio.run(main())))


def measure(seconds: float, rounds: int, with_dk: bool) -> dict[str, Any]:
    """Every configuration ``rounds`` times, interleaved (ours, Donkeycar's, next viewer count, ...), so that a
    burst of load from elsewhere on the machine lands on both controllers alike."""
    results: dict[str, Any] = {"machine": describe(), "seconds": seconds, "rounds": rounds, "rate_hz": RATE_HZ}
    kinds = ["ours"] + (["donkeycar"] if with_dk else [])
    runs: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for _ in range(rounds):
        for n in VIEWERS:
            for kind in kinds:
                runs.setdefault((kind, n), []).append(run_blocking(drive(kind, n, seconds)))
    for (kind, n), got in runs.items():
        results.setdefault(kind, {})[str(n)] = summarise(got)
    return results


def table(results: dict[str, Any]) -> str:
    t = PrettyTable(
        ["controller", "viewers", "CPU %", "lateness p99 ms", "cmd->memory p50/p99 ms", "arrival->PWM", "fps/viewer"]
    )
    for kind in ("ours", "donkeycar"):
        for n, r in results.get(kind, {}).items():
            t.add_row(
                [
                    "asyncdonkey" if kind == "ours" else "Donkeycar 5.3",
                    n,
                    f"{r['cpu_pct']:.1f}",
                    f"{r['lateness_p99_ms']:.2f}",
                    f"{r['latency_p50_ms']:.1f} / {r['latency_p99_ms']:.1f}",
                    "n/a" if r["to_pwm_p50_ms"] is None else f"{r['to_pwm_p50_ms']:.1f} / {r['to_pwm_p99_ms']:.1f}",
                    f"{r['frames_per_s_per_viewer']:.0f}",
                ]
            )
    return f"{t}\nmachine: {results['machine']}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="measured seconds per configuration and round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of every configuration (medians are shown)")
    parser.add_argument("--quick", action="store_true", help="one round of 2 s per configuration")
    parser.add_argument("--no-donkeycar", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--viewer-process", metavar="SPEC", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.viewer_process:
        viewer_process(json.loads(args.viewer_process))
        return 0
    logging.disable(logging.WARNING)
    with_dk = LocalWebController is not None and not args.no_donkeycar
    results = measure(2.0 if args.quick else args.seconds, 1 if args.quick else args.rounds, with_dk)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
