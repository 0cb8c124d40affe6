"""What a 60 Hz hardware poller costs on its own: asyncdonkey's ``Poller`` beside a Donkeycar-style threaded part.

Donkeycar's threaded parts poll a sensor as ``while on: value = read(); time.sleep(period)`` (its IMU part,
for one); a ``Poller`` keeps absolute deadlines, timestamps and numbers every sample, and skips and counts
overruns. Both cost one wake-up per sample, and a wake-up dominates: right after it every line of Python runs
on cold caches. Printed, for each, medians over the repetitions:

  * CPU per sample of the poller's thread (µs): the read stamps ``time.thread_time()``; the figure is the median
    difference between successive samples, i.e. everything the thread does per sample, sleep included,
  * process CPU per wall second (% of one core), start and stop included,
  * and the ratio ours / Donkeycar-style, taken per repetition and then the median.

The two run **at the same time**, each in its own process (so they share the machine's noise: CPU figures on a
busy or virtual machine move by tens of percent over minutes, and only side-by-side figures compare), for
``--seconds`` each repetition, alternating which starts first.

    python benchmarks/poller.py              # 10 repetitions of 3 s
    python benchmarks/poller.py --reps 4     # a quick look
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import logging
import statistics
import subprocess
import sys
import threading
import time

RATE_HZ = 60.0


def _stamped(cpu: list[float]):
    def read() -> float:
        cpu.append(time.thread_time())
        return 0.5

    return read


def _ours(seconds: float, cpu: list[float]) -> None:
    import uvloop

    from asyncdonkey import Poller

    poller = Poller(_stamped(cpu), RATE_HZ, name="imu")

    async def main() -> None:
        task = asyncio.ensure_future(poller.update())
        await asyncio.sleep(seconds)
        poller.shutdown()
        await task

    loop = uvloop.new_event_loop()
    try:
        loop.run_until_complete(main())
    finally:
        loop.close()


def _donkey_style(seconds: float, cpu: list[float]) -> None:
    read = _stamped(cpu)

    class ThreadedSensor:  # the shape of Donkeycar's threaded sensor parts
        def __init__(self) -> None:
            self.period = 1.0 / RATE_HZ
            self.value = None
            self.on = True

        def update(self) -> None:
            while self.on:
                self.value = read()
                time.sleep(self.period)

    part = ThreadedSensor()
    thread = threading.Thread(target=part.update)
    thread.start()
    time.sleep(seconds)
    part.on = False
    thread.join()


def _worker(kind: str, seconds: float) -> None:
    """One run in this process; prints its figures as JSON."""
    logging.disable(logging.INFO)
    import uvloop  # noqa: F401

    import asyncdonkey  # noqa: F401  (imports stay out of the measured window)

    cpu: list[float] = []
    t0, c0 = time.monotonic(), time.process_time()
    (_ours if kind == "ours" else _donkey_style)(seconds, cpu)
    process_pct = (time.process_time() - c0) / (time.monotonic() - t0) * 100
    steady = cpu[5:]  # the thread's first samples warm up
    per_sample = statistics.median(b - a for a, b in itertools.pairwise(steady)) * 1e6
    print(json.dumps({"per_sample_us": per_sample, "process_pct": process_pct, "samples": len(cpu)}))


def measure(reps: int, seconds: float) -> dict[str, dict[str, float]]:
    runs: dict[str, list[dict[str, float]]] = {"ours": [], "donkey": []}
    for rep in range(reps):
        kinds = ["ours", "donkey"] if rep % 2 == 0 else ["donkey", "ours"]
        procs = [
            (
                k,
                subprocess.Popen(
                    [sys.executable, __file__, "--worker", k, "--seconds", str(seconds)],
                    stdout=subprocess.PIPE,
                    text=True,
                ),
            )
            for k in kinds
        ]
        for k, p in procs:
            out, _ = p.communicate()
            if p.returncode:
                raise SystemExit(f"poller benchmark: the {k} worker failed (exit {p.returncode})")
            runs[k].append(json.loads(out))
    result: dict[str, dict[str, float]] = {}
    for k, rs in runs.items():
        result[k] = {f: statistics.median(r[f] for r in rs) for f in ("per_sample_us", "process_pct")}
    for f in ("per_sample_us", "process_pct"):
        ratios = [a[f] / b[f] for a, b in zip(runs["ours"], runs["donkey"], strict=True) if b[f] > 0]
        result.setdefault("ratio", {})[f] = statistics.median(ratios)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reps", type=int, default=10)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--worker", choices=["ours", "donkey"], help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        _worker(args.worker, args.seconds)
        return 0
    from machine_info import describe

    result = measure(args.reps, args.seconds)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"{RATE_HZ:.0f} Hz poller alone, {args.reps} x {args.seconds:g} s side by side; {describe(with_load=True)}")
    print(f"{'':24s}{'asyncdonkey':>14s}{'Donkeycar-style':>17s}{'ours / theirs':>15s}")
    for f, label, unit in (("per_sample_us", "thread CPU per sample", "µs"), ("process_pct", "process CPU", "%")):
        ours, theirs, ratio = result["ours"][f], result["donkey"][f], result["ratio"][f]
        print(f"{label + ' (' + unit + ')':24s}{ours:14.2f}{theirs:17.2f}{ratio:15.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
