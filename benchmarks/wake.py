"""What waking up at a deadline costs on this machine, one way of waiting after another: the floor under every
periodic loop's CPU, and where the drive loop's cost beside Donkeycar's comes from.

Each way wakes ``--rate`` times a second, at the deadlines of one schedule, and does nothing else; the figure is
the process CPU time per wake-up (µs) from the first wake-up to the last (no loop or timer started or stopped
in it), the median over interleaved repetitions (their order rotated each time):

  * ``sleep``: a thread's ``time.sleep`` of the time left to each deadline, as Donkeycar's loop and threaded
    parts wait (and asyncdonkey's pollers),
  * ``timerfd read``: a blocking ``read()`` of a periodic timerfd,
  * ``epoll``: Python's ``select.epoll`` watching that timerfd, and the ``read()``,
  * ``uvloop``: uvloop watching it (``add_reader``), a callback that reads it: the event loop's own share,
  * ``asyncio``: the same on asyncio's own loop,
  * ``asyncdonkey waiter``: ``DeadlineWaiter.call_at(..., period=)`` on uvloop, a callback that returns the next
    deadline: what the drive loop's wait costs, without the tick.

The gap between the first and the last is what an asyncio runtime pays per tick over a thread that sleeps,
before it runs any part. Linux only (timerfd).

    python benchmarks/wake.py               # 20 Hz, 5 repetitions of 3 s each
    python benchmarks/wake.py --rate 100
    python benchmarks/wake.py --json        # figures as JSON for benchmarks/run_all.py
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import select
import statistics
import sys
import time
from collections.abc import Callable

from prettytable import PrettyTable

from asyncdonkey.clock import DeadlineWaiter, _timerfd
from asyncdonkey.loop import run_blocking
from machine_info import describe

FULL = {"reps": 5, "seconds": 3.0}
QUICK = {"reps": 3, "seconds": 1.0}


def _periodic_timerfd(period_s: float) -> _timerfd.Timerfd:
    tfd = _timerfd.Timerfd()
    interval = round(period_s * 1e9)
    tfd.arm_every(time.monotonic_ns() + interval, interval)
    return tfd


# Each way wakes ``wakes`` times and returns the process CPU time from its first wake-up to its last: what the
# wake-ups in between cost, without starting and stopping a loop or a timer.


def wake_sleep(period_s: float, wakes: int) -> float:
    sleep, now, cpu = time.sleep, time.monotonic, time.process_time
    t0 = now()
    sleep(period_s)
    c0 = cpu()
    for k in range(2, wakes + 1):
        left = t0 + k * period_s - now()
        if left > 0:
            sleep(left)
    return cpu() - c0


def wake_timerfd_read(period_s: float, wakes: int) -> float:
    tfd = _periodic_timerfd(period_s)
    try:
        os.set_blocking(tfd.fd, True)
        read, fd = os.read, tfd.fd
        read(fd, 8)
        c0 = time.process_time()
        for _ in range(wakes - 1):
            read(fd, 8)
        return time.process_time() - c0
    finally:
        tfd.close()


def wake_epoll(period_s: float, wakes: int) -> float:
    tfd = _periodic_timerfd(period_s)
    ep = select.epoll()
    try:
        ep.register(tfd.fd, select.EPOLLIN)
        poll, read, fd = ep.poll, os.read, tfd.fd
        poll()
        read(fd, 8)
        c0 = time.process_time()
        for _ in range(wakes - 1):
            poll()
            read(fd, 8)
        return time.process_time() - c0
    finally:
        ep.close()
        tfd.close()


def _on_loop(use_uvloop: bool, period_s: float, wakes: int) -> float:
    async def main() -> float:
        loop = asyncio.get_running_loop()
        done = loop.create_future()
        tfd = _periodic_timerfd(period_s)
        read, fd, cpu = os.read, tfd.fd, time.process_time
        seen = [0, 0.0]

        def on_readable() -> None:
            read(fd, 8)
            n = seen[0] = seen[0] + 1
            if n == 1:
                seen[1] = cpu()
            elif n == wakes:
                loop.remove_reader(fd)
                done.set_result(cpu() - seen[1])

        loop.add_reader(fd, on_readable)
        try:
            return await done
        finally:
            tfd.close()

    return run_blocking(main(), use_uvloop=use_uvloop)


def wake_uvloop(period_s: float, wakes: int) -> float:
    return _on_loop(True, period_s, wakes)


def wake_asyncio(period_s: float, wakes: int) -> float:
    return _on_loop(False, period_s, wakes)


def wake_waiter(period_s: float, wakes: int) -> float:
    async def main() -> float:
        done = asyncio.get_running_loop().create_future()
        cpu = time.process_time
        t0 = time.monotonic() + period_s
        k = 0
        c0 = 0.0

        def tick() -> float | None:
            nonlocal k, c0
            k += 1
            if k == 1:
                c0 = cpu()
            elif k == wakes:
                done.set_result(cpu() - c0)
                return None
            return t0 + k * period_s

        with DeadlineWaiter() as waiter:
            waiter.call_at(t0, tick, period=period_s)
            return await done

    return run_blocking(main())


WAYS: dict[str, Callable[[float, int], float]] = {
    "sleep": wake_sleep,
    "timerfd read": wake_timerfd_read,
    "epoll": wake_epoll,
    "uvloop": wake_uvloop,
    "asyncio": wake_asyncio,
    "asyncdonkey waiter": wake_waiter,
}


def cpu_per_wake_us(way: Callable[[float, int], float], rate_hz: float, seconds: float) -> float:
    wakes = max(round(rate_hz * seconds), 3)
    return way(1.0 / rate_hz, wakes) / (wakes - 1) * 1e6


def measure(rate_hz: float, reps: int, seconds: float) -> dict:
    if not _timerfd.AVAILABLE:
        raise SystemExit("wake benchmark: needs Linux timerfd")
    names = list(WAYS)
    for name in names:  # warm every path once
        cpu_per_wake_us(WAYS[name], rate_hz, min(seconds, 0.2))
    runs: dict[str, list[float]] = {name: [] for name in names}
    for rep in range(reps):
        shift = rep % len(names)
        for name in names[shift:] + names[:shift]:
            runs[name].append(cpu_per_wake_us(WAYS[name], rate_hz, seconds))
    return {
        "rate_hz": rate_hz,
        "reps": reps,
        "seconds": seconds,
        "machine": describe(with_load=True),
        "us_per_wake": {name: statistics.median(v) for name, v in runs.items()},
        "us_per_wake_runs": runs,
    }


def report(results: dict) -> str:
    pt = PrettyTable(["way of waiting", "CPU per wake-up (µs), median", "min-max", "over sleep (µs)"])
    base = results["us_per_wake"]["sleep"]
    for name, us in results["us_per_wake"].items():
        runs = results["us_per_wake_runs"][name]
        pt.add_row([name, f"{us:.0f}", f"{min(runs):.0f}-{max(runs):.0f}", f"{us - base:+.0f}"])
    return (
        f"{pt.get_string()}\n{results['rate_hz']:g} Hz, median of {results['reps']} interleaved repetitions of "
        f"{results['seconds']:g} s; {results['machine']}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=20.0, help="wake-ups per second (default 20)")
    ap.add_argument("--reps", type=int, help=f"repetitions (default {FULL['reps']})")
    ap.add_argument("--seconds", type=float, help=f"seconds per repetition and way (default {FULL['seconds']})")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK['reps']} repetitions of {QUICK['seconds']} s")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    opts = dict(QUICK if args.quick else FULL)
    if args.reps is not None:
        opts["reps"] = args.reps
    if args.seconds is not None:
        opts["seconds"] = args.seconds
    results = measure(args.rate, opts["reps"], opts["seconds"])
    print(json.dumps(results, indent=2) if args.json else report(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
