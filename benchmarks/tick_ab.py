"""The drive loop's CPU per tick, this tree's ``Drive`` against another ``drive.py``, in paired rounds.

A change to the tick (a refactor, a new feature on the hot path) should be judged by what it costs per tick, and
on a shared machine a before/after pair of separate runs says little: CPU moves by tens of percent over minutes
(two runs of the *same* code, a minute apart in separate interpreters, differed by up to 60 % a round). So both
versions run in one interpreter: the other ``drive.py`` (``--before``, a copy of the old file) is loaded as a
module of the package beside the current one, and each run hands ``Vehicle.run()`` one or the other ``Drive``
class. Round after round every car runs once with each (order alternating), a fraction of a second apart, and the
figure is the median over rounds of the *paired* difference per tick (current - before), beside each side's
median.

The cars (``Stamp`` first, as in ``benchmarks/loop.py``; a tick's CPU is the loop thread's ``time.thread_time``
from the first tick's stamp to the last's over the ticks in between, so a drive's start and end-of-drive report
are not in it):

* ``idle flat``: the stamp alone, run flat out (a rate far above what the loop can do, on uvloop, the deadline
  timer's callback driving the ticks); every tick overruns its period here;
* ``10 parts flat``: the stamp and 10 trivial sync parts, flat out;
* ``idle virtual`` / ``10 parts virtual``: the same at 20 Hz on :class:`~asyncdonkey.VirtualClockLoop`, where no
  tick overruns (the virtual loop's jump to each deadline is in the figure, the same on both sides);
* ``10 parts, 1 async virtual``: one of the 10 parts is ``async def run``, so the drive task resumes the ticks
  and awaits that part every tick.

Under load even paired medians move by a percent or two, so ``--opcodes`` adds a figure no load moves: the
bytecodes executed per tick in the code of the two ``drive.py`` files (a tracer counts them over 200 and 400
ticks; the difference over 200 is the per-tick count, without the drive's start and end). It counts
instructions, not their cost, but a refactor that keeps the hot path's bytecode keeps its cost.

    cp src/asyncdonkey/core/drive.py /tmp/drive_before.py      # before the change
    python benchmarks/tick_ab.py --before /tmp/drive_before.py --rounds 30
    python benchmarks/tick_ab.py --before /tmp/drive_before.py --opcodes

A change that spans modules (the plan, the pipelines and the drive together) cannot be loaded beside this tree
one file at a time. ``--base-tree`` compares two whole trees instead: each side is a worker interpreter that
imports its own tree's ``src`` (``PYTHONPATH``) and stays up for the whole comparison, warm; the rounds alternate
requests to the two, one run at a time, so the pairs are still a fraction of a second apart and only one side
runs at once. ``--opcodes`` then counts the bytecodes of every file of each side's package (the plan's closures
the tick calls are in the figure, not only ``drive.py``), and of its ``drive.py`` alone:

    git worktree add /tmp/wt-base HEAD                     # before the change
    python benchmarks/tick_ab.py --base-tree /tmp/wt-base --rounds 30 --opcodes
    git worktree remove /tmp/wt-base
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import asyncdonkey.loop
from asyncdonkey import Vehicle, VirtualClockLoop
from asyncdonkey.loop import run_blocking

Drive = asyncdonkey.loop.Drive  # this tree's

N_PARTS = 10


class Stamp:
    """The car's first part: the loop thread's CPU time at each tick's start."""

    def __init__(self) -> None:
        self.cpu: list[float] = []

    def run(self) -> None:
        self.cpu.append(time.thread_time())


class Noop:
    def run(self, x=None):
        return x


class AsyncNoop:
    async def run(self, x=None):
        return x


CONFIGS = {  # name: (parts after the stamp, how many of them async, virtual clock)
    "idle flat": (0, 0, False),
    "10 parts flat": (N_PARTS, 0, False),
    "idle virtual": (0, 0, True),
    "10 parts virtual": (N_PARTS, 0, True),
    "10 parts, 1 async virtual": (N_PARTS, 1, True),
}


def load_before(path: str) -> type:
    """The ``Drive`` class of another ``drive.py``, loaded as a module of this asyncdonkey (its relative imports
    resolve here), so only the drive differs between the two sides. It must be a ``drive.py`` of
    ``asyncdonkey.core`` whose ``Drive`` runs its own lifecycle (``Drive.run``, which ``Vehicle.run`` awaits); to
    compare with an older tree, compare whole trees (``--base-tree``)."""
    spec = importlib.util.spec_from_file_location("asyncdonkey.core._drive_before", path)
    if spec is None or spec.loader is None:
        raise SystemExit(f"tick_ab: cannot load {path} as a module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module.Drive


def us_per_tick(drive_cls: type, config: tuple[int, int, bool], ticks: int) -> float:
    n_parts, n_async, virtual = config
    v = Vehicle()
    stamp = Stamp()
    v.add(stamp)
    for i in range(n_parts):
        v.add(AsyncNoop() if i < n_async else Noop(), inputs=[f"c{i}"], outputs=[f"c{i + 1}"])
    asyncdonkey.loop.Drive = drive_cls
    gc.collect()
    if virtual:
        with asyncio.Runner(loop_factory=VirtualClockLoop) as runner:
            runner.run(v.run(20, ticks))
    else:
        run_blocking(v.run(1e9, ticks), use_uvloop=True)
    c = stamp.cpu
    if len(c) != ticks:
        raise RuntimeError(f"tick_ab: {len(c)} ticks ran, {ticks} asked for")
    return (c[-1] - c[0]) / (len(c) - 1) * 1e6


#: one side of a comparison: ``measure(car name, ticks)`` → CPU µs per tick
Measure = Callable[[str, int], float]


def in_process(drive_cls: type) -> Measure:
    return lambda name, ticks: us_per_tick(drive_cls, CONFIGS[name], ticks)


def compare(before: Measure, after: Measure, rounds: int, ticks: int, repeats: int) -> dict[str, dict[str, float]]:
    pairs: dict[str, list[tuple[float, float]]] = {name: [] for name in CONFIGS}
    paired_rounds(before, after, range(rounds), ticks, repeats, pairs)
    return summarise(pairs)


def paired_rounds(
    before: Measure,
    after: Measure,
    rounds: range,
    ticks: int,
    repeats: int,
    pairs: dict[str, list[tuple[float, float]]],
) -> None:
    """Warm both sides up, then run ``rounds``, appending each car's (before, after) minimums to ``pairs``."""
    for side in (before, after):  # warm up both (imports, caches, the specializing interpreter)
        for name in CONFIGS:
            side(name, 1000)
    for rnd in rounds:
        for name in CONFIGS:
            a: list[float] = []
            b: list[float] = []
            for rep in range(repeats):  # A B A B ... (B A B A ... every other round)
                first, second = ((before, a), (after, b)) if (rnd + rep) % 2 == 0 else ((after, b), (before, a))
                first[1].append(first[0](name, ticks))
                second[1].append(second[0](name, ticks))
            pairs[name].append((min(a), min(b)))


def summarise(pairs: dict[str, list[tuple[float, float]]]) -> dict[str, dict[str, float]]:
    out = {}
    for name, p in pairs.items():
        rel = [(b - a) / a * 100 for a, b in p]
        out[name] = {
            "before_us": statistics.median(a for a, _ in p),
            "after_us": statistics.median(b for _, b in p),
            "diff_us": statistics.median(b - a for a, b in p),
            "diff_pct": statistics.median(rel),
            "q1_pct": statistics.quantiles(rel, n=4)[0],
            "q3_pct": statistics.quantiles(rel, n=4)[2],
            "after_less": sum(b < a for a, b in p),
        }
    return out


def opcodes_per_tick(drive_cls: type, config: tuple[int, int, bool], under: str | None = None) -> float:
    """Bytecodes executed per tick in the code of ``drive_cls``'s module (its file), or with ``under`` in every
    file under that directory, by a tracer."""
    filename = sys.modules[drive_cls.__module__].__file__
    count = [0]

    def counted(name: str) -> bool:
        return name.startswith(under) if under is not None else name == filename

    def opcode(frame, event, arg):
        if event == "opcode":
            count[0] += 1
        return opcode

    def call(frame, event, arg):
        if not counted(frame.f_code.co_filename):
            return None
        frame.f_trace_opcodes = True
        return opcode

    counts = []
    for ticks in (200, 400):
        count[0] = 0
        sys.settrace(call)
        try:
            us_per_tick(drive_cls, config, ticks)
        finally:
            sys.settrace(None)
        counts.append(count[0])
    return (counts[1] - counts[0]) / 200


# ------------------------------------------------------------------------------------------ whole trees
def worker() -> int:
    """``--worker``: answer requests on stdin, one JSON line each, with this interpreter's asyncdonkey (the tree its
    ``PYTHONPATH`` names): ``{"car": name, "ticks": n}`` → µs per tick, ``{"opcodes": name}`` → bytecodes per
    tick in the package's files and in its ``drive.py``."""
    package = str(Path(asyncdonkey.loop.__file__).parent) + os.sep
    print(json.dumps({"package": package}), flush=True)
    for line in sys.stdin:
        req = json.loads(line)
        if "opcodes" in req:
            config = CONFIGS[req["opcodes"]]
            out: object = [opcodes_per_tick(Drive, config, package), opcodes_per_tick(Drive, config)]
        else:
            out = us_per_tick(Drive, CONFIGS[req["car"]], req["ticks"])
        print(json.dumps(out), flush=True)
    return 0


class Tree:
    """A worker interpreter running another tree's asyncdonkey (``tree/src``), kept up between requests."""

    def __init__(self, tree: Path) -> None:
        env = dict(os.environ, PYTHONPATH=str(tree / "src"))
        self.proc = subprocess.Popen(
            [sys.executable, __file__, "--worker"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
        )
        self.package = self._ask(None)["package"]
        if not self.package.startswith(str(tree.resolve())):
            raise SystemExit(f"tick_ab: the worker for {tree} imported asyncdonkey from {self.package}")

    def _ask(self, req: object) -> object:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        if req is not None:
            self.proc.stdin.write(json.dumps(req) + "\n")
            self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"tick_ab: the worker for {self.package if req else 'a tree'} died")
        return json.loads(line)

    def __call__(self, name: str, ticks: int) -> float:
        return float(self._ask({"car": name, "ticks": ticks}))

    def opcodes(self, name: str) -> list[float]:
        return self._ask({"opcodes": name})

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self.proc.wait(30)


def compare_trees(base: Path, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """The two trees round by round, in a fresh pair of workers every ``--respawn`` rounds.

    Why fresh workers: two interpreters running the *same* tree differ by a few percent for as long as they live
    (where their objects landed in memory, their hash seeds), which a comparison of one pair would read as the
    change's cost; over many pairs that bias is spread on both sides and the median of the differences drops it.
    """
    here = Path(__file__).resolve().parents[1]
    pairs: dict[str, list[tuple[float, float]]] = {name: [] for name in CONFIGS}
    for first in range(0, args.rounds, args.respawn):
        before, after = Tree(base), Tree(here)
        try:
            if args.opcodes and first == 0:
                print(f"{'car':27} bytecodes per tick, before and after: in the package {'':8} in drive.py")
                for name in CONFIGS:
                    (pb, db), (pa, da) = before.opcodes(name), after.opcodes(name)
                    print(f"{name:27} {pb:8.1f} {pa:8.1f} {'':26} {db:8.1f} {da:8.1f}")
            rounds = range(first, min(first + args.respawn, args.rounds))
            paired_rounds(before, after, rounds, args.ticks, args.repeats, pairs)
        finally:
            before.close()
            after.close()
    return summarise(pairs)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    side = ap.add_mutually_exclusive_group(required=True)
    side.add_argument("--before", help="the other drive.py (a copy of the file before a change)")
    side.add_argument("--base-tree", type=Path, help="the other tree, whole (a git worktree of the commit before)")
    side.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--ticks", type=int, default=3_000, help="ticks per run")
    ap.add_argument("--repeats", type=int, default=3, help="runs per side and round (the minimum counts)")
    ap.add_argument("--respawn", type=int, default=1, help="with --base-tree: new worker pair every N rounds")
    ap.add_argument("--opcodes", action="store_true", help="also count the bytecodes per tick of each side")
    args = ap.parse_args(argv)
    if args.rounds < 2 or args.ticks < 2 or args.repeats < 1 or args.respawn < 1:
        ap.error("--rounds and --ticks must be >= 2, --repeats and --respawn >= 1")
    if args.worker:
        return worker()
    if args.base_tree is not None:
        out = compare_trees(args.base_tree, args)
    else:
        before = load_before(args.before)
        if args.opcodes:
            print(f"{'car':27} bytecodes per tick in drive.py: before, after")
            for name, config in CONFIGS.items():
                print(f"{name:27} {opcodes_per_tick(before, config):8.1f} {opcodes_per_tick(Drive, config):8.1f}")
        out = compare(in_process(before), in_process(Drive), args.rounds, args.ticks, args.repeats)
        asyncdonkey.loop.Drive = Drive
    print(f"{args.rounds} paired rounds, min of {args.repeats} runs of {args.ticks} ticks a side")
    print("CPU µs per tick of the loop thread: medians over rounds; diff: after - before, paired by round")
    print(f"{'car':27} {'before':>8} {'after':>8} {'diff µs':>8} {'diff %':>7} {'IQR of diff %':>15} after<before")
    for name, r in out.items():
        iqr = f"{r['q1_pct']:+.1f}..{r['q3_pct']:+.1f}"
        print(
            f"{name:27} {r['before_us']:8.2f} {r['after_us']:8.2f} {r['diff_us']:+8.3f} {r['diff_pct']:+7.2f} "
            f"{iqr:>15} {r['after_less']}/{args.rounds}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
