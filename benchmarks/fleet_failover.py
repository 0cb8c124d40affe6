"""A fleet on a primary pilot server and its standby: kill -9 of the primary, then its return.

    python benchmarks/fleet_failover.py [--cars 4] [--rounds 3]

Each round pairs a fresh fleet (``make_fleet(..., standby=)``, mutual TLS on loopback), starts the primary and
the standby (``asyncdonkey pilot-server`` on the shipped ``sim_pilot.onnx``) and one car process per car
(``tests/net/fleet_car.py``, 20 Hz, its own ``StaleCommandStop`` of 250 ms), lets them drive 3 s on the
primary, kills the primary with SIGKILL, drives 3 s on the standby, starts the primary again and drives 3 s
more. Per car it reports the longest time without a command around the kill and around the hand-back, whether
its failsafe fired (its throttle went to 0.0 after it first drove), and the answers it counted twice for one
frame (``duplicates``), both servers alive and in total.
"""

from __future__ import annotations

import argparse
import itertools
import signal
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.net.fleet_car import record_sim_frames  # noqa: E402
from tests.net.standby_fleet import StandbyFleet  # noqa: E402


def longest_gap(arrivals: list[float], t0: float, t1: float) -> float:
    ts = [t0, *[t for t in arrivals if t0 < t < t1], t1]
    return max(b - a for a, b in itertools.pairwise(ts))


def one_round(work: Path, cars: list[str], frames: Path) -> list[dict]:
    fleet = StandbyFleet(work / "fleet", cars)
    primary, standby = fleet.server(fleet.files.server_config), fleet.server(fleet.files.standby_config)
    procs = fleet.car_processes(frames)
    deadline = time.monotonic() + 60
    while not all(p.of("driving") for p in procs):
        if time.monotonic() > deadline:
            raise RuntimeError("the cars did not drive: " + "".join(p.lines[-1] if p.lines else "" for p in procs))
        time.sleep(0.05)
    t_all = max(p.of("driving")[0]["t"] for p in procs)
    time.sleep(3.0)
    t_kill = time.monotonic()
    primary.p.send_signal(signal.SIGKILL)
    primary.stop()
    time.sleep(3.0)
    t_back = time.monotonic()
    primary = fleet.server(fleet.files.server_config)
    time.sleep(6.0)  # the primary starts (~1-2 s), takes its cars back, drives
    t_end = time.monotonic()
    for p in (*procs, primary, standby):
        p.stop()
    rows = []
    for r in (r for p in procs for r in p.of("report")):
        arrivals = r["arrivals"]
        both = [t for t in arrivals if t_all < t < t_kill]
        rows.append(
            {
                "car": r["car"],
                "gap_kill_ms": 1e3 * longest_gap(arrivals, t_kill - 0.5, t_back),
                "gap_back_ms": 1e3 * longest_gap(arrivals, t_back, t_end),
                "failsafe": any(v == 0.0 for t, v in r["throttle_changes"] if t_all < t < t_end),
                "commands_both_alive": len(both),
                "duplicates": r["counters"]["duplicates"],
            }
        )
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cars", type=int, default=4, help="car processes (default 4)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    args = ap.parse_args()
    cars = [f"car{i + 1}" for i in range(args.cars)]
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "frames.npy"
        record_sim_frames(str(frames), count=12)
        for k in range(args.rounds):
            rows = one_round(Path(tmp) / f"r{k}", cars, frames)
            for row in rows:
                print(
                    f"round {k + 1} {row['car']}: longest gap at the kill {row['gap_kill_ms']:.0f} ms, at the"
                    f" hand-back {row['gap_back_ms']:.0f} ms; failsafe fired: {row['failsafe']}; duplicates"
                    f" {row['duplicates']} (commands while the primary answered: {row['commands_both_alive']})",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
