"""The virtual clock's speed: how long 10,000 ticks of a 20 Hz car (500 s of driving) take, and where it goes.

Prints, best of several runs, in real seconds per 10,000 ticks:
  * the car: ``asyncdonkey.Vehicle`` with 10 trivial sync parts at 20 Hz on ``VirtualClockLoop``,
  * the loop alone: one task sleeping to the next 20 Hz deadline 10,000 times (a timer, a future, a jump:
    what the car asks of the loop each tick), on ``VirtualClockLoop``,
  * the same task on a plain asyncio loop with the timers replaced by ``call_soon`` (no waiting at all): the
    cost of an asyncio loop iteration, the floor any virtual loop sits on,
  * the loop beside a daemon thread: each jump first waits ``autojump_threshold`` (1 ms) of real time for it,
    so this is measured on 200 ticks and shown per 10,000.

The car's own work (its parts, memory and profiler) is the car's figure minus the loop's.

    python benchmarks/virtual_clock.py           # 7 runs of each
    python benchmarks/virtual_clock.py --quick   # 3 runs
    python benchmarks/virtual_clock.py --json    # figures as JSON for benchmarks/run_all.py
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import threading
import time

from asyncdonkey import Vehicle
from asyncdonkey.virtual_loop import VirtualClockLoop
from machine_info import describe

TICKS = 10_000
RATE_HZ = 20
N_PARTS = 10


class Noop:
    def run(self, x=None):
        return x


def car_seconds() -> float:
    v = Vehicle()
    for i in range(N_PARTS):
        v.add(Noop(), inputs=[f"c{i}"], outputs=[f"c{i + 1}"])
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        t = time.perf_counter()
        report = runner.run(v.run(RATE_HZ, TICKS))
        elapsed = time.perf_counter() - t
    assert report.loops == TICKS, report.loops
    return elapsed


async def _ticks(n: int, use_timers: bool) -> None:
    loop = asyncio.get_running_loop()
    for k in range(1, n + 1):
        fut = loop.create_future()
        if use_timers:
            loop.call_at(k / RATE_HZ, fut.set_result, None)
        else:
            loop.call_soon(fut.set_result, None)
        await fut


def loop_seconds(virtual: bool, n: int = TICKS) -> float:
    factory = VirtualClockLoop if virtual else asyncio.SelectorEventLoop
    with asyncio.Runner(loop_factory=factory) as runner:
        t = time.perf_counter()
        runner.run(_ticks(n, use_timers=virtual))
        return time.perf_counter() - t


def beside_a_daemon_thread_seconds(n: int = 200) -> float:
    stop = threading.Event()

    def update_loop() -> None:  # a Donkeycar part's update(): real time, never calls the loop
        while not stop.is_set():
            time.sleep(0.001)

    thread = threading.Thread(target=update_loop, daemon=True)
    with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
        thread.start()
        try:
            t = time.perf_counter()
            runner.run(_ticks(n, use_timers=True))
            return (time.perf_counter() - t) * TICKS / n
        finally:
            stop.set()
            thread.join()


def measure(runs: int) -> dict:
    car = min(car_seconds() for _ in range(runs))
    virtual = min(loop_seconds(True) for _ in range(runs))
    plain = min(loop_seconds(False) for _ in range(runs))
    threaded = min(beside_a_daemon_thread_seconds() for _ in range(max(1, runs // 3)))
    return {
        "ticks": TICKS,
        "runs": runs,
        "car_s": car,
        "loop_s": virtual,
        "plain_asyncio_s": plain,
        "car_minus_loop_s": car - virtual,
        "beside_daemon_thread_s": threaded,
        "per_tick_us": {"car": car / TICKS * 1e6, "loop": virtual / TICKS * 1e6, "plain_asyncio": plain / TICKS * 1e6},
        "machine": describe(),
    }


def table(r: dict) -> str:
    us = r["per_tick_us"]
    rows = [
        (f"car, {N_PARTS} sync parts", f"{r['car_s']:.3f} s", f"{us['car']:.1f} µs/tick"),
        ("loop alone (timer + jump)", f"{r['loop_s']:.3f} s", f"{us['loop']:.1f} µs/tick"),
        ("plain asyncio, no timers", f"{r['plain_asyncio_s']:.3f} s", f"{us['plain_asyncio']:.1f} µs/tick"),
        ("the car's own work", f"{r['car_minus_loop_s']:.3f} s", ""),
        ("loop beside a daemon thread", f"{r['beside_daemon_thread_s']:.1f} s", "1 ms autojump threshold per jump"),
    ]
    lines = [f"{r['ticks']:,} ticks at {RATE_HZ} Hz on the virtual clock (best of {r['runs']}):"]
    lines += [f"  {a:<28} {b:>8}   {c}".rstrip() for a, b, c in rows]
    lines.append(f"machine: {r['machine']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 runs of each instead of 7")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    results = measure(3 if args.quick else 7)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
