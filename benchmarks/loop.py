"""Drive-loop timing and CPU cost: rate error, tick lateness, CPU per wall second, per-part overhead, beside
Donkeycar's Vehicle.

The car: 10 trivial parts plus a 60 Hz hardware poller (ours: a ``Poller``; Donkeycar's: a threaded part that
reads and sleeps a period, as its IMU does). Prints, for 20, 100 and 1000 Hz:
  * long-run rate error in ppm: the slope of a least-squares line through the tick start times against the
    period asked for (the two endpoints alone would measure their own jitter, not the rate),
  * tick lateness p50 / p99 / max in ms: tick start minus its ideal time ``t_first + k / rate_hz`` (ours: minus
    its deadline, as the loop reports it, so a skipped deadline does not count as every later tick being late),
  * CPU: process CPU time per wall second between the first and the last tick (all threads: the loop, the
    poller, Donkeycar's threads), in percent of one core,
for asyncdonkey in its default mode (timerfd waits, no spinning), in precise mode (``run(precise=True)``: the
last stretch before each deadline is spun, with a learned window) and Donkeycar. Also:
  * idle CPU: the same 10 parts with no poller at 20 Hz, what the loop itself costs,
  * per-part overhead in µs: the cost the loop adds around a trivial part, profiling on, measured flat out
    as (tick time with N parts - tick time with none) / N.

When ``donkeycar`` is importable the same car runs on its ``Vehicle`` in the same process and the ratios
are printed. asyncdonkey runs on uvloop (as ``Vehicle.start`` does) unless ``--no-uvloop``.

    python benchmarks/loop.py            # 1,000 ticks per rate (about four minutes with Donkeycar)
    python benchmarks/loop.py --quick    # 200 ticks per rate
    python benchmarks/loop.py --json     # figures as JSON for benchmarks/run_all.py
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Poller, Vehicle
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
PRECISE_RATES = (20, 100)
N_PARTS = 10
POLL_HZ = 60
IDLE_HZ = 20


class Stamp:
    """First part of the graph: records when each tick started (time.monotonic, same for both loops) and the
    process CPU time then."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.cpu: list[float] = []

    def run(self) -> None:
        self.times.append(time.monotonic())
        self.cpu.append(time.process_time())


class Noop:
    def run(self, x=None):
        return x


def sensor_read() -> float:
    """The poller's "device": trivial, so the figures are the runtime's cost, not the read's."""
    return 0.5


class DonkeyStylePoller:
    """A sensor as Donkeycar's threaded parts poll one (its IMU, for one): read, sleep the period, repeat."""

    def __init__(self, rate_hz: float) -> None:
        self.period = 1.0 / rate_hz
        self.value = None
        self.on = True

    def update(self) -> None:
        while self.on:
            self.value = sensor_read()
            time.sleep(self.period)

    def run_threaded(self):
        return self.value

    def shutdown(self) -> None:
        self.on = False


def _graph(vehicle, n_parts: int, poller: str | None = None) -> Stamp:
    stamp = Stamp()
    vehicle.add(stamp)
    for i in range(n_parts):
        vehicle.add(Noop(), inputs=[f"c{i}"], outputs=[f"c{i + 1}"])
    if poller == "ours":
        vehicle.add(Poller(sensor_read, POLL_HZ, name="imu"), outputs=["imu"])
    elif poller == "donkeycar":
        vehicle.add(DonkeyStylePoller(POLL_HZ), outputs=["imu"], threaded=True)
    return stamp


def _timing(stamp: Stamp, rate_hz: float) -> dict[str, float]:
    t = np.asarray(stamp.times)
    n = len(t)
    k = np.arange(n)
    period = np.polyfit(k, t - t[0], 1)[0]  # least-squares seconds per tick
    late = (t - (t[0] + k / rate_hz)) * 1e3
    cpu = np.asarray(stamp.cpu)
    return {
        "rate_error_ppm": float((1.0 / period / rate_hz - 1.0) * 1e6),
        "lateness_p50_ms": float(np.percentile(late, 50)),
        "lateness_p99_ms": float(np.percentile(late, 99)),
        "lateness_max_ms": float(late.max()),
        "cpu_pct": float((cpu[-1] - cpu[0]) / (t[-1] - t[0]) * 100),
    }


def _settle() -> None:
    """Let the previous run's threads finish, so they are not billed to the next one."""
    deadline = time.monotonic() + 2.0
    while threading.active_count() > 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.2)


def ours_rate(rate_hz: float, ticks: int, use_uvloop: bool, precise: bool = False, poller: bool = True) -> dict:
    _settle()
    v = Vehicle()
    stamp = _graph(v, N_PARTS, "ours" if poller else None)
    report = run_blocking(v.run(rate_hz, ticks, precise=precise), use_uvloop=use_uvloop)
    out = _timing(stamp, rate_hz)
    # Lateness against each tick's own deadline, as the loop measures it: when a stall made the loop skip a
    # deadline, the ticks after it are due one period later, not "late by a period" from then on.
    late = report.lateness_ms
    out.update(
        lateness_p50_ms=late["50%"],
        lateness_p99_ms=late["99%"],
        lateness_max_ms=late["max"],
        skipped_deadlines=report.skipped_deadlines,
    )
    return out


def donkey_rate(rate_hz: float, ticks: int, poller: bool = True) -> dict:
    _settle()
    v = DonkeyVehicle()
    stamp = _graph(v, N_PARTS, "donkeycar" if poller else None)
    v.start(rate_hz=rate_hz, max_loop_count=ticks)
    return _timing(stamp, rate_hz)


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
        if rate in PRECISE_RATES:
            row["ours_precise"] = ours_rate(rate, n, use_uvloop, precise=True)
        if with_donkey:
            row["donkeycar"] = donkey_rate(rate, n)
        results["rates"][str(rate)] = row
    idle_ticks = max(ticks // 5, 100)
    results["idle_cpu_pct"] = {"ours": ours_rate(IDLE_HZ, idle_ticks, use_uvloop, poller=False)["cpu_pct"]}
    if with_donkey:
        results["idle_cpu_pct"]["donkeycar"] = donkey_rate(IDLE_HZ, idle_ticks, poller=False)["cpu_pct"]
    results["overhead_us"] = {"ours": ours_overhead(20_000, use_uvloop)}
    if with_donkey:
        results["overhead_us"]["donkeycar"] = donkey_overhead(20_000)
    return results


LABELS = {"ours": "asyncdonkey", "ours_precise": "asyncdonkey precise", "donkeycar": donkeycar_label()}


def table(results: dict) -> str:
    has_dk = "donkeycar" in results["overhead_us"]
    pt = PrettyTable()
    pt.field_names = ["rate", "loop", "rate error (ppm)", "lateness p50 (ms)", "p99 (ms)", "max (ms)", "CPU (%)"]
    for rate, row in results["rates"].items():
        for who, label in LABELS.items():
            if who not in row:
                continue
            r = row[who]
            pt.add_row(
                [
                    f"{rate} Hz",
                    label,
                    f"{r['rate_error_ppm']:+,.1f}",
                    f"{r['lateness_p50_ms']:.3f}",
                    f"{r['lateness_p99_ms']:.3f}",
                    f"{r['lateness_max_ms']:.3f}",
                    f"{r['cpu_pct']:.2f}",
                ]
            )
    out = [pt.get_string()]
    ov = results["overhead_us"]
    line = f"per-part overhead (profiling on): asyncdonkey {ov['ours']:.2f} µs"
    if has_dk:
        line += f", donkeycar {ov['donkeycar']:.2f} µs (ratio {ov['ours'] / ov['donkeycar']:.2f})"
    out.append(line)
    idle = results["idle_cpu_pct"]
    line = f"idle CPU ({N_PARTS} no-op parts, no poller, {IDLE_HZ} Hz): asyncdonkey {idle['ours']:.2f} %"
    if has_dk:
        line += f", donkeycar {idle['donkeycar']:.2f} % (ratio {idle['ours'] / idle['donkeycar']:.2f})"
    out.append(line)
    if has_dk:
        for rate, row in results["rates"].items():
            ours, dk = row["ours"], row["donkeycar"]
            ratio = abs(dk["rate_error_ppm"]) / max(abs(ours["rate_error_ppm"]), 1.0)
            out.append(
                f"{rate} Hz: Donkeycar's rate error is {ratio:,.0f}x ours"
                f" ({dk['rate_error_ppm']:+,.0f} vs {ours['rate_error_ppm']:+,.1f} ppm);"
                f" CPU ours/Donkeycar {ours['cpu_pct'] / dk['cpu_pct']:.2f}"
                + (f", precise {row['ours_precise']['cpu_pct'] / dk['cpu_pct']:.2f}" if "ours_precise" in row else "")
            )
    out.append(
        f"machine: {results['machine']}; {results['ticks']} ticks per rate (x5 at 1 kHz);"
        f" {N_PARTS} parts + a {POLL_HZ} Hz poller"
    )
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
