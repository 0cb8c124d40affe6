"""A fleet on one pilot server: frame-to-command latency, the server's CPU, batched against one call per frame.

The server is ``asyncdonkey pilot-server`` (another process), the cars light processes of
``tests/net/fleet_car.py``: each car a Vehicle with its own Zenoh session, replaying simulator frames recorded
once (160x120 RGB) at 20 Hz, taking its commands (``cars/<car>/pilot/command``) and holding them through a
``StaleCommandStop`` of 250 ms, four cars per process. For 1, 4, 8, 16, 24 and 32 cars, the server runs the same
model twice: with a dynamic batch (one call per batch, window 5 ms) and with its batch fixed at 1 (one call per
frame). Figures per run, over the measured seconds after every car drives:

* **frame-to-command latency** per car, measured on the car: the command's arrival minus the origin of the
  frame it answers (the car's capture time, carried to the server and back): the pooled p50 and p99 over every
  car, and the worst car's p99;
* **answered**: commands taken over frames sent, and the slowest car's command rate;
* **the server's CPU** (its process, % of one core), the mean batch, the model's time per batch p50/p99 (one
  call, or one call per frame with the batch fixed at 1);
* **the machine**: every core's busy share, and of it the benchmark's own processes (cars and server).

A run **saturates** when some car gets fewer than 90 % of its frames answered or its p99 passes the 250 ms
failsafe window (those cars would stop). The model is Donkeycar's ``KerasLinear`` shape with seeded weights
(``asyncdonkey.pilot_export.export_donkey_linear_shaped``: the compute of a real Donkeycar pilot), made
batchable by ``dynamic_batch_onnx``. Wire figures per car at 20 Hz (payload and the 24-byte age attachment;
Zenoh's framing, 10-60 bytes per sample, and TCP/TLS not counted): frames raw and JPEG q85, commands.

Loopback only (127.0.0.1, plain TCP, no scouting), Zenoh's shared memory off (as between machines). The cars run
on the same two cores as the server: at 16 cars they take a share of the machine a real fleet would not.

    python benchmarks/fleet.py              # about 5 minutes
    python benchmarks/fleet.py --quick      # 1 and 4 cars, about a minute
    python benchmarks/fleet.py --json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
# benchmarks/zenoh.py is named like the Eclipse Zenoh package: keep this folder off the path while importing
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != HERE]
import numpy as np  # noqa: E402

sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT / "tests" / "net"))
from fleet_car import FleetProcess, record_sim_frames  # noqa: E402

from machine_info import describe  # noqa: E402

RATE_HZ = 20.0
FAILSAFE_MS = 250.0
CARS_PER_PROCESS = 4
CAR_SCRIPT = ROOT / "tests" / "net" / "fleet_car.py"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cpu_ticks(pid: int | None = None) -> int:
    """CPU time of a process (utime + stime), or every core's busy time, in clock ticks."""
    if pid is None:
        fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return sum(fields) - fields[3] - fields[4]
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[11]) + int(fields[12])


def _configs(folder: Path, port: int) -> tuple[Path, Path]:
    """The server's and the cars' Zenoh configs: loopback TCP, no scouting, no shared memory."""
    common = {"scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}
    common["transport"] = {"shared_memory": {"enabled": False}}
    server = {"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}, **common}
    car = {
        "mode": "peer",
        "listen": {"endpoints": []},
        "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "exit_on_failure": False},
        **common,
    }
    (folder / "server.json5").write_text(json.dumps(server))
    (folder / "car.json5").write_text(json.dumps(car))
    return folder / "server.json5", folder / "car.json5"


#: the server's final line (ServerFigures.line): batches, frames per batch, time per batch, model calls
_FINAL = re.compile(
    r"final: .*\| (\d+) batches(?: \(\d+ failed\))?, ([\d.]+) frames per batch, per batch p50 ([\d.]+) ms p99"
    r" ([\d.]+) ms \| (\d+) model calls"
)


def run_fleet(n: int, model: Path, frames: Path, folder: Path, seconds: float) -> dict[str, Any]:
    """One run: a server on ``model`` and ``n`` cars; the figures of the module docstring."""
    port = _free_port()
    server_cfg, car_cfg = _configs(folder, port)
    names = [f"car{k + 1:02d}" for k in range(n)]
    command = ["-m", "asyncdonkey.commands", "pilot-server", str(model), "--cars", *names]
    server = FleetProcess([*command, "--config", str(server_cfg), "--stats-every", "0"], cwd=ROOT)
    cars: list[FleetProcess] = []
    try:
        end = time.monotonic() + 30
        while not any(line.startswith("pilot server:") for line in server.lines):
            if time.monotonic() > end or server.p.poll() is not None:
                raise SystemExit(f"fleet.py: the server did not start:\n{''.join(server.lines[-10:])}")
            time.sleep(0.05)
        for k in range(0, n, CARS_PER_PROCESS):
            args = [str(CAR_SCRIPT), "--frames", str(frames), "--config", str(car_cfg), "--hz", str(RATE_HZ)]
            for name in names[k : k + CARS_PER_PROCESS]:
                args += ["--car", name]
            cars.append(FleetProcess(args, cwd=ROOT))
        end = time.monotonic() + 30  # a saturated server may never answer some cars: measured as it is
        while sum(len(p.of("driving")) for p in cars) < n and time.monotonic() < end:
            time.sleep(0.05)
        time.sleep(1.0)  # settle
        pids = [server.p.pid, *(p.p.pid for p in cars)]
        t0, machine0 = time.monotonic(), _cpu_ticks()
        server0, own0 = _cpu_ticks(server.p.pid), sum(_cpu_ticks(p) for p in pids)
        time.sleep(seconds)
        t1 = time.monotonic()
        hz, cores = os.sysconf("SC_CLK_TCK"), os.cpu_count() or 1
        wall = t1 - t0
        server_cpu = (_cpu_ticks(server.p.pid) - server0) / hz / wall * 100
        machine = (_cpu_ticks() - machine0) / hz / wall / cores * 100
        own = (sum(_cpu_ticks(p) for p in pids) - own0) / hz / wall / cores * 100
    finally:
        for p in cars:
            p.stop(timeout=20.0)
        server.stop(timeout=20.0)
    reports = [r for p in cars for r in p.of("report")]
    lat_all: list[float] = []
    car_p99, rates, answered = [], [], []
    for r in reports:
        arrivals, lat = np.array(r["arrivals"]), np.array(r["latency_ms"])
        inside = (arrivals >= t0) & (arrivals < t1)
        lat_all += lat[inside].tolist()
        car_p99.append(float(np.percentile(lat[inside], 99)) if inside.any() else float("inf"))
        rates.append(int(inside.sum()) / wall)
        answered.append(r["commands"] / max(1, r["frames_sent"]))
    final = next((m for line in server.lines if (m := _FINAL.search(line))), None)
    out = {
        "cars": n,
        "latency_p50_ms": float(np.percentile(lat_all, 50)) if lat_all else None,
        "latency_p99_ms": float(np.percentile(lat_all, 99)) if lat_all else None,
        "worst_car_p99_ms": max(car_p99) if car_p99 else None,
        "slowest_car_hz": min(rates) if rates else 0.0,
        "answered_min": min(answered) if answered else 0.0,
        "server_cpu_pct": server_cpu,
        "machine_busy_pct": machine,
        "benchmark_busy_pct": own,
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        "seconds": wall,
    }
    if final:
        out |= {
            "batches": int(final[1]),
            "batch_mean": float(final[2]),
            "model_call_p50_ms": float(final[3]),  # per batch (the name the recorded results have)
            "model_call_p99_ms": float(final[4]),
            "model_calls": int(final[5]),
        }
    out["driving"] = sum(1 for r in reports if r["commands"] > 0)
    out["saturated"] = bool(
        len(reports) < n
        or out["driving"] < n
        or out["answered_min"] < 0.9
        or out["worst_car_p99_ms"] is None
        or out["worst_car_p99_ms"] > FAILSAFE_MS
    )
    return out


def wire(frames: np.ndarray) -> dict[str, Any]:
    """Bytes per second per car at 20 Hz: frames raw and JPEG q85 (mean over the recorded frames), commands."""
    from asyncdonkey.parts.zenoh.codec import ATTACHMENT, encode, encode_group

    raw = encode(frames[0], "cam/image_array").payload
    jpeg = [len(encode(f, "cam/image_array", jpeg_quality=85).payload) for f in frames]
    command = encode_group({"pilot/angle": -0.0482, "pilot/throttle": 0.4850}, "pilot/command").payload
    att = ATTACHMENT.size
    return {
        "frame_raw_bytes": len(raw),
        "frame_jpeg_bytes": float(np.mean(jpeg)),
        "command_bytes": len(command),
        "attachment_bytes": att,
        "raw_bytes_per_s": (len(raw) + att) * RATE_HZ,
        "jpeg_bytes_per_s": (float(np.mean(jpeg)) + att) * RATE_HZ,
        "command_bytes_per_s": (len(command) + att) * RATE_HZ,
    }


def measure(quick: bool, counts: list[int] | None = None, seconds: float | None = None) -> dict[str, Any]:
    from asyncdonkey.parts.zenoh.batch_infer import dynamic_batch_onnx
    from asyncdonkey.pilot_export import export_donkey_linear_shaped

    counts = counts or ([1, 4] if quick else [1, 4, 8, 16, 24, 32])
    seconds = seconds or (4.0 if quick else 8.0)
    with tempfile.TemporaryDirectory(prefix="fleet-bench-") as tmp:
        folder = Path(tmp)
        frames_path = folder / "frames.npy"
        frames = record_sim_frames(str(frames_path), count=40)
        fixed = export_donkey_linear_shaped(folder / "donkey_linear.onnx")
        batched = dynamic_batch_onnx(fixed, folder / "donkey_linear_batch.onnx")
        runs: dict[str, list[dict[str, Any]]] = {"batched": [], "per_frame": []}
        for n in counts:
            for mode, model in (("batched", batched), ("per_frame", fixed)):
                r = run_fleet(n, model, frames_path, folder, seconds)
                runs[mode].append(r)
                print(
                    f"  {n:2d} cars {mode:9s}: p50 {r['latency_p50_ms']:.1f} ms p99 {r['latency_p99_ms']:.1f} ms,"
                    f" server {r['server_cpu_pct']:.0f} %, machine {r['machine_busy_pct']:.0f} %",
                    file=sys.stderr,
                )
    saturates = {mode: next((r["cars"] for r in rs if r["saturated"]), None) for mode, rs in runs.items()}
    return {
        "machine": describe(with_load=True),
        "model": "Donkeycar KerasLinear shape (export_donkey_linear_shaped), batch dynamic vs fixed at 1",
        "rate_hz": RATE_HZ,
        "window_ms": 5.0,
        "seconds": seconds,
        "quick": quick,
        "runs": runs,
        "saturates_at": saturates,
        "wire": wire(frames),
    }


def table(r: dict[str, Any]) -> str:
    lines = [
        f"fleet on one pilot server ({r['model']}), {r['rate_hz']:g} Hz per car, window {r['window_ms']:g} ms,"
        f" {r['seconds']:g} s per run",
        "| cars | calls | frame→command p50 / p99 (ms) | worst car p99 | slowest car Hz | answered | server CPU %"
        " | batch mean | model time per batch p50 / p99 (ms) | machine busy % (ours) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for mode, rs in r["runs"].items():
        for x in rs:
            lines.append(
                f"| {x['cars']} | {mode.replace('_', ' ')} | {x['latency_p50_ms']:.1f} / {x['latency_p99_ms']:.1f}"
                f" | {x['worst_car_p99_ms']:.1f} | {x['slowest_car_hz']:.1f} | {x['answered_min'] * 100:.0f} %"
                f" | {x['server_cpu_pct']:.0f} | {x.get('batch_mean', 0):.1f}"
                f" | {x.get('model_call_p50_ms', 0):.2f} / {x.get('model_call_p99_ms', 0):.2f}"
                f" | {x['machine_busy_pct']:.0f} ({x['benchmark_busy_pct']:.0f}) |"
            )
    sat = r["saturates_at"]
    lines.append("")
    lines.append(
        "saturates at: "
        + ", ".join(f"{m.replace('_', ' ')} {v if v is not None else 'beyond the counts run'}" for m, v in sat.items())
    )
    w = r["wire"]
    lines.append(
        f"wire per car at {r['rate_hz']:g} Hz: frames raw {w['raw_bytes_per_s'] / 1e3:.0f} kB/s"
        f" ({w['frame_raw_bytes']} B each), JPEG q85 {w['jpeg_bytes_per_s'] / 1e3:.1f} kB/s"
        f" ({w['frame_jpeg_bytes']:.0f} B), commands {w['command_bytes_per_s'] / 1e3:.2f} kB/s"
        f" ({w['command_bytes']} B + {w['attachment_bytes']} B attachment)"
    )
    lines.append(f"machine: {r['machine']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="1 and 4 cars, 4 s each (about a minute)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    ap.add_argument("--cars", type=int, nargs="+", help="car counts to run (default 1 4 8 16 24 32)")
    ap.add_argument("--seconds", type=float, help="measured seconds per run (default 8, quick 4)")
    args = ap.parse_args(argv)
    results = measure(args.quick, args.cars, args.seconds)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
