"""Drive-loop timing: rate error, tick lateness and per-part overhead, beside Donkeycar's Vehicle.

Prints, for 20, 100 and 1000 Hz:
  * long-run rate error in ppm: (ticks - 1) / (last tick start - first tick start) against the requested rate,
  * tick lateness p50 / p99 / max in ms: tick start minus its ideal time ``t_first + k / rate_hz``,
  * per-part overhead in µs: the cost the loop adds around a trivial part, profiling on, measured flat out
    as (tick time with N parts - tick time with none) / N.

When ``donkeycar`` is importable the same graph runs on its ``Vehicle`` in the same process and the ratios
are printed. asyncdonkey runs on uvloop (as ``Vehicle.start`` does) unless ``--no-uvloop``.

    python benchmarks/loop.py            # 1,000 ticks per rate (about two minutes with Donkeycar)
    python benchmarks/loop.py --quick    # 200 ticks per rate
    python benchmarks/loop.py --json     # figures as JSON for benchmarks/run_all.py
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Vehicle
from asyncdonkey.loop import run_blocking
from machine_info import describe, donkeycar_label

try:  # Donkeycar prints a banner on import; keep it out of the figures
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from donkeycar.vehicle import Vehicle as DonkeyVehicle
except ImportError:  # pragma: no cover - donkeycar is optional
    DonkeyVehicle = None

RATES = (20, 100, 1000)
N_PARTS = 10


class Stamp:
    """First part of the graph: records when each tick started (time.monotonic, same for both loops)."""

    def __init__(self) -> None:
        self.times: list[float] = []

    def run(self) -> None:
        self.times.append(time.monotonic())


class Noop:
    def run(self, x=None):
        return x


def _graph(vehicle, n_parts: int) -> Stamp:
    stamp = Stamp()
    vehicle.add(stamp)
    for i in range(n_parts):
        vehicle.add(Noop(), inputs=[f"c{i}"], outputs=[f"c{i + 1}"])
    return stamp


def _timing(times: list[float], rate_hz: float) -> dict[str, float]:
    t = np.asarray(times)
    n = len(t)
    achieved = (n - 1) / (t[-1] - t[0])
    ideal = t[0] + np.arange(n) / rate_hz
    late = (t - ideal) * 1e3
    return {
        "rate_error_ppm": (achieved / rate_hz - 1.0) * 1e6,
        "lateness_p50_ms": float(np.percentile(late, 50)),
        "lateness_p99_ms": float(np.percentile(late, 99)),
        "lateness_max_ms": float(late.max()),
    }


def ours_rate(rate_hz: float, ticks: int, use_uvloop: bool) -> dict[str, float]:
    v = Vehicle()
    stamp = _graph(v, N_PARTS)
    run_blocking(v.run(rate_hz, ticks), use_uvloop=use_uvloop)
    return _timing(stamp.times, rate_hz)


def donkey_rate(rate_hz: float, ticks: int) -> dict[str, float]:
    v = DonkeyVehicle()
    stamp = _graph(v, N_PARTS)
    v.start(rate_hz=rate_hz, max_loop_count=ticks)
    return _timing(stamp.times, rate_hz)


def ours_overhead(ticks: int, use_uvloop: bool) -> float:
    """µs per part: flat-out ticks (rate far above what the loop can do) with and without parts."""

    def per_tick(n_parts: int) -> float:
        v = Vehicle()
        _graph(v, n_parts)
        t = time.perf_counter()
        run_blocking(v.run(1e9, ticks), use_uvloop=use_uvloop)
        return (time.perf_counter() - t) / ticks

    base = min(per_tick(0) for _ in range(3))
    full = min(per_tick(N_PARTS * 2) for _ in range(3))
    return (full - base) / (N_PARTS * 2) * 1e6


def donkey_overhead(ticks: int) -> float:
    def per_tick(n_parts: int) -> float:
        v = DonkeyVehicle()
        _graph(v, n_parts)
        t = time.perf_counter()
        for _ in range(ticks):
            v.update_parts()  # the body of Donkeycar's loop, profiler included, without its sleep
        return (time.perf_counter() - t) / ticks

    base = min(per_tick(0) for _ in range(3))
    full = min(per_tick(N_PARTS * 2) for _ in range(3))
    return (full - base) / (N_PARTS * 2) * 1e6


def measure(ticks: int, use_uvloop: bool, with_donkey: bool) -> dict:
    results: dict = {"ticks": ticks, "uvloop": use_uvloop, "rates": {}, "machine": describe()}
    for rate in RATES:
        n = ticks if rate <= 100 else ticks * 5
        row = {"ours": ours_rate(rate, n, use_uvloop)}
        if with_donkey:
            row["donkeycar"] = donkey_rate(rate, n)
        results["rates"][str(rate)] = row
    results["overhead_us"] = {"ours": ours_overhead(20_000, use_uvloop)}
    if with_donkey:
        results["overhead_us"]["donkeycar"] = donkey_overhead(20_000)
    return results


def table(results: dict) -> str:
    has_dk = "donkeycar" in results["overhead_us"]
    pt = PrettyTable()
    cols = ["rate", "loop", "rate error (ppm)", "lateness p50 (ms)", "p99 (ms)", "max (ms)"]
    pt.field_names = cols
    for rate, row in results["rates"].items():
        for who in ("ours", "donkeycar"):
            if who not in row:
                continue
            r = row[who]
            pt.add_row(
                [
                    f"{rate} Hz",
                    "asyncdonkey" if who == "ours" else donkeycar_label(),
                    f"{r['rate_error_ppm']:+,.0f}",
                    f"{r['lateness_p50_ms']:.3f}",
                    f"{r['lateness_p99_ms']:.3f}",
                    f"{r['lateness_max_ms']:.3f}",
                ]
            )
    out = [pt.get_string()]
    ov = results["overhead_us"]
    line = f"per-part overhead (profiling on): asyncdonkey {ov['ours']:.2f} µs"
    if has_dk:
        line += f", donkeycar {ov['donkeycar']:.2f} µs (ratio {ov['ours'] / ov['donkeycar']:.2f})"
    out.append(line)
    if has_dk:
        for rate, row in results["rates"].items():
            ours, dk = row["ours"]["rate_error_ppm"], row["donkeycar"]["rate_error_ppm"]
            ratio = abs(dk) / max(abs(ours), 1.0)
            out.append(f"{rate} Hz: Donkeycar's rate error is {ratio:,.0f}x ours ({dk:+,.0f} vs {ours:+,.0f} ppm)")
    out.append(f"machine: {results['machine']}; {results['ticks']} ticks per rate (x5 at 1 kHz)")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=1000)
    parser.add_argument("--quick", action="store_true", help="200 ticks per rate")
    parser.add_argument("--no-uvloop", action="store_true")
    parser.add_argument("--no-donkeycar", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    logging.disable(logging.INFO)  # the per-run profiler reports are not the figures
    ticks = 200 if args.quick else args.ticks
    results = measure(ticks, not args.no_uvloop, DonkeyVehicle is not None and not args.no_donkeycar)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
