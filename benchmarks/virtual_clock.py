"""The virtual clock's speed: how long 10,000 ticks of a 20 Hz car (500 s of driving) take, and where it goes.

Prints, as the median of several interleaved runs (each round runs every workload once), in real seconds per
10,000 ticks and in microseconds per tick:
  * the car: ``asyncdonkey.Vehicle`` with 10 trivial sync parts at 20 Hz on ``VirtualClockLoop``,
  * the loop alone, three ways, so its own overhead shows apart from the car's:
      - a task awaiting a future that a timer resolves, 10,000 times (a future, a timer, a jump and a task step:
        what a task-driven tick asks of the loop; two loop iterations per tick),
      - a task running ``await asyncio.sleep(period)`` 10,000 times (the same through asyncio's own sleep),
      - a bare ``loop.call_at`` chain, a callback scheduling itself one period later 10,000 times (a timer and a
        jump per tick, one loop iteration, no task: what a tick run straight from a timer costs the loop),
      - the same chain through a timer that queues the callback with ``call_soon`` (two iterations per tick: how
        the drive runs an all-sync car's tick on the virtual clock, so that ticks and tasks due at the same
        instant keep their order),
  * plain asyncio doing the two task-free and task-driven cases with ``call_soon`` instead of timers (no waiting
    at all): what asyncio's own iteration costs per pass, a select() system call included,
  * the loop beside a daemon thread: each jump first waits ``autojump_threshold`` (1 ms) of real time for it,
    so this is measured on 200 ticks and shown per 10,000.

The car's own work (its parts, memory and profiler, and the report at the end) is the car's figure minus the
timer queueing a callback.

    python benchmarks/virtual_clock.py           # 7 rounds
    python benchmarks/virtual_clock.py --quick   # 3 rounds
    python benchmarks/virtual_clock.py --json    # figures as JSON for benchmarks/run_all.py
    python benchmarks/virtual_clock.py --profile call_at_chain_s   # where one workload's time goes (cProfile)
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import threading
import time
from collections.abc import Callable

from asyncdonkey import Vehicle
from asyncdonkey.clock.virtual_loop import VirtualClockLoop
from machine_info import describe

TICKS = 10_000
RATE_HZ = 20
PERIOD = 1 / RATE_HZ
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
            loop.call_at(k * PERIOD, fut.set_result, None)
        else:
            loop.call_soon(fut.set_result, None)
        await fut


async def _sleeps(n: int) -> None:
    loop = asyncio.get_running_loop()
    for k in range(1, n + 1):
        await asyncio.sleep(k * PERIOD - loop.time())


async def _chain(n: int, how: str) -> None:
    """A callback that schedules itself ``n`` times: "timer" a period later, "timer, then queued" a period later
    through a timer that queues it with call_soon, "queued" at once with call_soon."""
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    left = [n]

    def tick() -> None:
        left[0] -= 1
        if not left[0]:
            done.set_result(None)
        elif how == "timer":
            loop.call_at(loop.time() + PERIOD, tick)
        elif how == "timer, then queued":
            loop.call_at(loop.time() + PERIOD, loop.call_soon, tick)
        else:
            loop.call_soon(tick)

    tick()
    await done


def _timed(factory: Callable[[], asyncio.AbstractEventLoop], main: Callable[[], object]) -> float:
    with asyncio.Runner(loop_factory=factory) as runner:
        t = time.perf_counter()
        runner.run(main())  # type: ignore[arg-type]
        return time.perf_counter() - t


def loop_seconds(virtual: bool, n: int = TICKS) -> float:
    """A task awaiting a future resolved by a timer (virtual) or by call_soon (plain asyncio), ``n`` times."""
    factory = VirtualClockLoop if virtual else asyncio.SelectorEventLoop
    return _timed(factory, lambda: _ticks(n, use_timers=virtual))


def sleep_loop_seconds(n: int = TICKS) -> float:
    """A task awaiting ``asyncio.sleep`` to the next deadline ``n`` times, on the virtual clock."""
    return _timed(VirtualClockLoop, lambda: _sleeps(n))


def chain_seconds(how: str, n: int = TICKS) -> float:
    """A callback scheduling itself ``n`` times (see ``_chain``): on the virtual clock with timers, on plain
    asyncio when "queued"."""
    factory = asyncio.SelectorEventLoop if how == "queued" else VirtualClockLoop
    return _timed(factory, lambda: _chain(n, how))


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


WORKLOADS: dict[str, Callable[[], float]] = {
    "car_s": car_seconds,
    "loop_s": lambda: loop_seconds(True),
    "sleep_loop_s": sleep_loop_seconds,
    "call_at_chain_s": lambda: chain_seconds("timer"),
    "timer_call_soon_chain_s": lambda: chain_seconds("timer, then queued"),
    "plain_asyncio_s": lambda: loop_seconds(False),
    "plain_call_soon_chain_s": lambda: chain_seconds("queued"),
}


def measure(runs: int) -> dict:
    times: dict[str, list[float]] = {name: [] for name in WORKLOADS}
    for _ in range(runs):  # interleaved: a slow minute on a shared machine slows every workload alike
        for name, workload in WORKLOADS.items():
            times[name].append(workload())
    figures = {name: statistics.median(ts) for name, ts in times.items()}
    threaded = statistics.median(beside_a_daemon_thread_seconds() for _ in range(max(1, runs // 3)))
    return {
        "ticks": TICKS,
        "runs": runs,
        **figures,
        "car_minus_loop_s": figures["car_s"] - figures["timer_call_soon_chain_s"],
        "beside_daemon_thread_s": threaded,
        "per_tick_us": {
            "car": figures["car_s"] / TICKS * 1e6,
            "loop": figures["loop_s"] / TICKS * 1e6,
            "sleep_loop": figures["sleep_loop_s"] / TICKS * 1e6,
            "call_at_chain": figures["call_at_chain_s"] / TICKS * 1e6,
            "timer_call_soon_chain": figures["timer_call_soon_chain_s"] / TICKS * 1e6,
            "plain_asyncio": figures["plain_asyncio_s"] / TICKS * 1e6,
            "plain_call_soon_chain": figures["plain_call_soon_chain_s"] / TICKS * 1e6,
        },
        "machine": describe(),
    }


def table(r: dict) -> str:
    us = r["per_tick_us"]
    rows = [
        (f"car, {N_PARTS} sync parts", f"{r['car_s']:.3f} s", f"{us['car']:.2f} µs/tick"),
        ("the car's own work", f"{r['car_minus_loop_s']:.3f} s", "car minus the timer queueing a callback"),
        ("loop: task awaits a timer", f"{r['loop_s']:.3f} s", f"{us['loop']:.2f} µs/tick  (2 iterations/tick)"),
        (
            "loop: asyncio.sleep loop",
            f"{r['sleep_loop_s']:.3f} s",
            f"{us['sleep_loop']:.2f} µs/tick  (2 iterations/tick)",
        ),
        (
            "loop: call_at chain",
            f"{r['call_at_chain_s']:.3f} s",
            f"{us['call_at_chain']:.2f} µs/tick  (1 iteration/tick)",
        ),
        (
            "loop: timer queueing a callback",
            f"{r['timer_call_soon_chain_s']:.3f} s",
            f"{us['timer_call_soon_chain']:.2f} µs/tick  (2 iterations/tick: the drive's all-sync tick)",
        ),
        ("plain asyncio: task, call_soon", f"{r['plain_asyncio_s']:.3f} s", f"{us['plain_asyncio']:.2f} µs/tick"),
        (
            "plain asyncio: call_soon chain",
            f"{r['plain_call_soon_chain_s']:.3f} s",
            f"{us['plain_call_soon_chain']:.2f} µs/tick",
        ),
        ("loop beside a daemon thread", f"{r['beside_daemon_thread_s']:.1f} s", "1 ms autojump threshold per jump"),
    ]
    lines = [f"{r['ticks']:,} ticks at {RATE_HZ} Hz on the virtual clock (median of {r['runs']} interleaved rounds):"]
    lines += [f"  {a:<31} {b:>8}   {c}".rstrip() for a, b, c in rows]
    lines.append(f"machine: {r['machine']}")
    return "\n".join(lines)


def profile(name: str, top: int = 25) -> None:
    """The workload's functions by their own time. cProfile adds a fixed cost to every call, so small
    functions look dearer than they are: compare variants with the figures, not with this."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    profiler.runcall(WORKLOADS[name])
    pstats.Stats(profiler).sort_stats("tottime").print_stats(top)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 rounds instead of 7")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument(
        "--profile",
        choices=sorted(WORKLOADS),
        help="no figures: run this workload once under cProfile and print where its time goes",
    )
    args = parser.parse_args(argv)
    if args.profile:
        profile(args.profile)
        return 0
    results = measure(3 if args.quick else 7)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
