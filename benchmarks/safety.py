"""Safety figures: the watchdog's time to neutral, what data provenance costs, and sensing-to-actuation latency.

    python benchmarks/safety.py            # full runs (about 40 s)
    python benchmarks/safety.py --quick    # a look
    python benchmarks/safety.py --json     # for run_all.py

* **Watchdog** (real loop, uvloop, PCA9685 register model behind the real smbus2 API): a car drives at half
  throttle with the stale-command failsafe wired (``throttle@age``, 250 ms window) when a sync part blocks the
  loop thread for a second, sleeping or spinning in Python with the GIL. Measured: from the moment the command
  went stale (its origin + the window) to the neutral pulse on the chip, and from the block's start. Donkeycar has
  no failsafe: its car drives on through any stall (the figure there is the block itself).
* **Provenance cost**: nanoseconds a part's output store takes with origins (the oldest-input rule, a declared
  selector's lookup, the in-place check) against the plain store the loop did before (value + write time), for a
  one-input part, an undeclared five-input selector, our ``DriveMode`` and a part returning its input array; and
  the per-part loop overhead, flat out, beside Donkeycar's ``Vehicle.update_parts``.
* **Safety process** (the car as a process of its own, ``tests/safety/guarded_car.py``, on a PCA9685 model this
  process serves): after ``kill -9`` of the car, ms until both outputs show their safe pulses; with a catastrophic
  regular expression holding the car's GIL in its pilot, ms from the hang's start to the stopped pulse (the
  throttle's deadline falls at most 250 ms after the start: its last command came before). And what the car
  pays for it: per tick the heartbeat (one store, one load), per command the deadline (two stores), in ns.
* **Checked mode**: nanoseconds a part's output store takes when checked against its channel's contract (the test
  default, ``Vehicle(checked=True)``) against the same store unchecked (the car's default), per checked output:
  a float command (``throttle``), a 120x160x3 camera frame, and the drive-mode selector's two commands.
* **Simulated car** (``examples/car.py``, real time, uvloop): sensing-to-actuation latency of the simulated car
  (frame age at the tick + pilot inference + the write), p50/p99/max, from the drive's report.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "examples"))
sys.path.insert(0, str(ROOT / "tests" / "safety"))

from asyncdonkey import Contracts, Memory, Vehicle  # noqa: E402
from asyncdonkey.core.plan import PartOptions, build_entry, checked_store  # noqa: E402
from asyncdonkey.loop import run_blocking  # noqa: E402
from machine_info import describe  # noqa: E402

WINDOW_S = 0.25
NEUTRAL = 370


def watchdog_trial(spin: bool, block_s: float = 1.0) -> tuple[float, float]:
    """(ms from stale deadline to neutral, ms from block start to neutral) for one blocked drive."""
    from rig import Const, Rig

    class Blocker:
        def __init__(self) -> None:
            self.k = 0
            self.started = 0.0

        def run(self) -> None:
            self.k += 1
            if self.k != 10:
                return
            self.k_blocked = self.k - 1  # index of this tick
            self.started = time.monotonic()
            end = self.started + block_s
            if spin:
                while time.monotonic() < end:
                    pass
            else:
                time.sleep(block_s)

    class Origin:
        """Remembers the origin of the command the throttle was given on each tick."""

        def __init__(self) -> None:
            self.origins: list[float] = []

        def run(self, age: float) -> None:
            self.origins.append(time.monotonic() - age)

    rig = Rig()
    v = Vehicle()
    v.add(Const(0.5), outputs=["throttle"])
    v.add(rig.throttle(), inputs=["throttle", "throttle@age"], name="throttle")
    origin = Origin()
    v.add(origin, inputs=["throttle@age"])
    blocker = Blocker()
    v.add(blocker)
    run_blocking(v.run(20, 15))
    rig.close()
    neutral = rig.pca.first_time(NEUTRAL, blocker.started)
    assert neutral is not None
    stale_at = origin.origins[blocker.k_blocked] + WINDOW_S  # the command in force when the loop blocked
    return (neutral - stale_at) * 1e3, (neutral - blocker.started) * 1e3


def watchdog(trials: int) -> dict:
    out = {}
    for spin in (False, True):
        late, since_block = zip(*(watchdog_trial(spin) for _ in range(trials)), strict=True)
        out["spinning" if spin else "sleeping"] = {
            "trials": trials,
            "after_deadline_p50_ms": float(np.percentile(late, 50)),
            "after_deadline_max_ms": float(np.max(late)),
            "since_block_p50_ms": float(np.percentile(since_block, 50)),
            "since_block_max_ms": float(np.max(since_block)),
        }
    return out


def _car_process(endpoint: str, scenario: str):
    import subprocess

    return subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "safety" / "guarded_car.py"), endpoint, scenario],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )


def _until(cond, timeout: float) -> float | None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return time.monotonic()
        time.sleep(0.0005)
    return None


def safety_process_trial(scenario: str) -> float:
    """ms to the safe state: after kill -9 (``drive``), or after the stale deadline (``regex``)."""
    import os
    import signal

    from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

    with I2CSimulator() as sim:
        pca = sim.attach(PCA9685Model(), address=0x40, bus=1)
        car = _car_process(sim.serve(), scenario)
        try:
            assert car.stdout is not None
            while car.stdout.readline().strip() != "driving":
                pass
            if scenario == "drive":
                t0 = time.monotonic()
                os.kill(car.pid, signal.SIGKILL)
                safe = _until(lambda: pca.pulse(0) == NEUTRAL and pca.pulse(1) == 375, 10.0)
            else:
                while car.stdout.readline().strip() != "hang":
                    pass
                t0 = time.monotonic()  # the stale deadline is at most WINDOW_S later (the last command came before)
                safe = _until(lambda: pca.pulse(0) == NEUTRAL, 10.0)
            assert safe is not None
            return (safe - t0) * 1e3
        finally:
            car.kill()
            car.communicate()


def safety_process(trials: int, n: int) -> dict:
    from asyncdonkey.hw.pca9685 import open_pwm_channel
    from asyncdonkey.safety import GuardedOutput, SafetyProcess
    from asyncdonkey.testing.i2c_models import I2CSimulator, PCA9685Model

    out: dict = {}
    for scenario, key in (("drive", "kill9_to_safe"), ("regex", "gil_held_since_hang")):
        ms = [safety_process_trial(scenario) for _ in range(trials)]
        out[key] = {"trials": trials, "p50_ms": float(np.percentile(ms, 50)), "max_ms": float(np.max(ms))}
    with I2CSimulator() as sim:
        sim.attach(PCA9685Model(), address=0x40, bus=1)
        sim.serve()
        ch = open_pwm_channel("PCA9685.1:40.0", buses=sim.registry())
        guard = SafetyProcess([GuardedOutput("throttle", ch.safety_route(NEUTRAL) or {}, None)], 10.0)
        guard.start()
        try:
            guard.ticking()
            beat, set_deadline = guard.beat, guard.deadline_setter(0)
            t = time.monotonic()

            def per_call_ns(fn, arg) -> float:
                best = float("inf")
                for _ in range(5):
                    t0 = time.perf_counter_ns()
                    for _ in range(n):
                        fn(arg)
                    best = min(best, (time.perf_counter_ns() - t0) / n)
                return best

            out["heartbeat_ns"] = per_call_ns(beat, t)
            out["deadline_ns"] = per_call_ns(set_deadline, t + 60.0)
        finally:
            guard.stop()
    return out


def _store_ns(store, value, args, n: int) -> float:
    t = time.perf_counter_ns()
    for _ in range(n):
        store(value, args, 1.0)
    return (time.perf_counter_ns() - t) / n


def provenance(n: int) -> dict:
    """ns per store: with origins (this runtime) vs the plain store (value + write time), for a one-input part, an
    undeclared five-input selector, our ``DriveMode`` (a declared selector) and a two-input part returning its input
    array (the in-place check, which looks through a Memory of 50 channels)."""
    from asyncdonkey.parts.control import DriveMode

    mem = Memory()
    mem.set("x", 1.0, origin=0.5)
    for k in ("user/angle", "user/throttle", "pilot/angle", "pilot/throttle", "imu"):
        mem.set(k, 0.3, origin=0.5)
    mem.set("user/mode", "local", origin=0.5)
    mem.set("cam/image_array", np.zeros((120, 160, 3), np.uint8), origin=0.4)
    for j in range(42):
        mem.set(f"other/{j}", float(j), origin=0.5)

    class One:
        def run(self, x):
            return x

    class Select:
        def run(self, m, ua, ut, pa, pt):
            return ua, ut

    class Fuse:
        def run(self, img, imu):
            return img

    def offload(fn):
        return fn

    def entry(part, name, ins, outs):
        return build_entry(mem, part, PartOptions(name=name, inputs=ins, outputs=outs), offload)

    drive_ins = ["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"]
    one = entry(One(), "one", ["x"], ["y"])
    sel = entry(Select(), "select", drive_ins, ["angle", "throttle"])
    dm = entry(DriveMode(), "drive_mode", drive_ins, ["angle", "throttle"])
    fuse = entry(Fuse(), "fuse", ["cam/image_array", "imu"], ["cam/fused"])
    d, stamps = mem.d, mem.stamps

    def plain_one(value, args, now):
        d["y"] = value
        stamps["y"] = now

    def plain_two(values, args, now):
        for k, v in zip(("angle", "throttle"), values, strict=True):
            d[k] = v
            stamps[k] = now

    args1, args5, args2 = one.args(), sel.args(), fuse.args()
    fresh = 2.0 + 0.0  # a new object
    res = {}
    for label, store, plain, value, args in (
        ("one_input", one.store, plain_one, fresh, args1),
        ("selector_5in_2out", sel.store, plain_two, (args5[1], fresh), args5),
        ("drive_mode_declared", dm.store, plain_two, dm.part.run(*args5), args5),
        ("input_array_returned", fuse.store, plain_one, args2[0], args2),
    ):
        ours = min(_store_ns(store, value, args, n) for _ in range(5))
        base = min(_store_ns(plain, value, args, n) for _ in range(5))
        res[label] = {"with_origins_ns": ours, "plain_ns": base, "added_ns": ours - base}
    return res


def checked_mode(n: int) -> dict:
    """ns per store checked against the contracts vs unchecked, and the difference per checked output."""
    mem = Memory()
    for k in ("x", "user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"):
        mem.set(k, 0.3, origin=0.5)
    contracts = Contracts()

    class Part:
        def run(self, *args):
            return None

    def offload(fn):
        return fn

    def entry(name: str, ins: list[str], outs: list[str]):
        return build_entry(mem, Part(), PartOptions(name=name, inputs=ins, outputs=outs), offload)

    frame = np.zeros((120, 160, 3), np.uint8)
    cases = (
        ("float_command", entry("pilot", ["x"], ["throttle"]), 0.25 + 0.0, 1),
        ("image_120x160x3", entry("camera", [], ["cam/image_array"]), frame, 1),
        ("selector_2_commands", entry("drive_mode", ["user/mode", "user/angle"], ["angle", "throttle"]), (0.1, 0.2), 2),
    )
    res = {}
    for label, e, value, outputs in cases:
        checked = checked_store(e.store, e.name, e.outputs, contracts)
        assert checked is not e.store
        args = e.args()
        ours = min(_store_ns(checked, value, args, n) for _ in range(5))
        base = min(_store_ns(e.store, value, args, n) for _ in range(5))
        res[label] = {
            "checked_ns": ours,
            "unchecked_ns": base,
            "outputs": outputs,
            "added_per_output_ns": (ours - base) / outputs,
        }
    return res


def loop_overhead(ticks: int) -> dict:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import loop as loop_bench

    figures = loop_bench.overhead(ticks, 3, True, loop_bench.DonkeyVehicle is not None)
    out = {"ours_us": figures["ours"]}
    if "donkeycar" in figures:
        out["donkeycar_us"] = figures["donkeycar"]
    return out


def sim_car_latency(seconds: float) -> dict:
    from car import make_car

    v, _car = make_car(seconds=seconds, status=None)
    report = run_blocking(v.run(20))
    lat = next(iter(report.latency_ms.values()), None) or {}
    return {
        "seconds": seconds,
        "p50_ms": lat.get("50%"),
        "p99_ms": lat.get("99%"),
        "max_ms": lat.get("max"),
        "pilot_p50_ms": (report.parts.get("OnnxPilot") or {}).get("50%"),
        "achieved_hz": report.achieved_hz,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)  # the watchdog's own warnings are the event being timed
    results = {
        "machine": describe(),
        "watchdog": watchdog(3 if args.quick else 10),
        "safety_process": safety_process(3 if args.quick else 10, 20_000 if args.quick else 200_000),
        "provenance": provenance(20_000 if args.quick else 200_000),
        "checked_mode": checked_mode(20_000 if args.quick else 200_000),
        "overhead": loop_overhead(5_000 if args.quick else 20_000),
        "sim_car": sim_car_latency(5.0 if args.quick else 15.0),
    }
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    print(f"safety figures on {results['machine']}")
    for kind, w in results["watchdog"].items():
        print(
            f"watchdog, loop blocked ({kind}): neutral {w['after_deadline_p50_ms']:.1f} ms after the stale deadline "
            f"(max {w['after_deadline_max_ms']:.1f}), {w['since_block_p50_ms']:.0f} ms after the block began "
            f"(max {w['since_block_max_ms']:.0f}); {w['trials']} trials"
        )
    sp = results["safety_process"]
    for key, what in (("kill9_to_safe", "after kill -9"), ("gil_held_since_hang", "GIL held, since the hang began")):
        f = sp[key]
        print(f"safety process, {what}: safe {f['p50_ms']:.1f} ms (max {f['max_ms']:.1f}); {f['trials']} trials")
    print(
        f"safety process, car's cost: heartbeat {sp['heartbeat_ns']:.0f} ns a tick, deadline {sp['deadline_ns']:.0f} ns"
    )
    for label, p in results["provenance"].items():
        print(
            f"provenance, {label}: store {p['with_origins_ns']:.0f} ns with origins vs {p['plain_ns']:.0f} ns plain "
            f"(+{p['added_ns']:.0f} ns)"
        )
    for label, c in results["checked_mode"].items():
        print(
            f"checked mode, {label}: store {c['checked_ns']:.0f} ns checked vs {c['unchecked_ns']:.0f} ns unchecked "
            f"(+{c['added_per_output_ns']:.0f} ns per checked output)"
        )
    ov = results["overhead"]
    dk = f", Donkeycar {ov['donkeycar_us']:.2f} µs" if "donkeycar_us" in ov else ""
    print(f"per-part loop overhead (provenance included): {ov['ours_us']:.2f} µs{dk}")
    s = results["sim_car"]
    print(
        f"simulated car, sensing-to-actuation: p50 {s['p50_ms']:.1f} ms, p99 {s['p99_ms']:.1f} ms, "
        f"max {s['max_ms']:.1f} ms (pilot p50 {s['pilot_p50_ms']:.2f} ms) at {s['achieved_hz']:.2f} Hz"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
