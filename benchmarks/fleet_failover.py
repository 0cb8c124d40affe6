"""A fleet on a primary pilot server and its standby: the primary is killed (or frozen), then it returns.

    python benchmarks/fleet_failover.py [--cars 4] [--rounds 3] [--fault kill|freeze]

Each round pairs a fresh fleet (``make_fleet(..., standby=)``, mutual TLS on loopback), starts the primary and
the standby (``asyncdonkey pilot-server`` on the shipped ``sim_pilot.onnx``) and one car process per car
(``tests/net/fleet_car.py``, 20 Hz, its own ``StaleCommandStop`` of 250 ms) and lets them drive 3 s on the
primary. Then the fault:

* ``kill`` (default): SIGKILL of the primary, whose sockets its OS closes at once; 3 s on the standby; the
  primary started again; 6 s more.
* ``freeze``: SIGSTOP of the primary, whose sockets stay open, as for a machine that hangs or loses power or its
  cable: its peers notice only when its Zenoh lease (1 s) runs out; 4 s; SIGCONT, so the same process resumes
  with whatever it held, and 6 s more.

Per car it reports the longest time without a command around the fault and around the hand-back, how long its
failsafe held the throttle at 0.0 after it first drove (none, for a takeover within the failsafe window), and
the answers it counted twice for one frame (``duplicates``), both servers alive and in total.
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


def stopped_s(changes: list[list[float]], t0: float, t1: float) -> float:
    """Time within (t0, t1) that the throttle spent at 0.0 (the failsafe's stop), from its logged changes."""
    total, since = 0.0, None
    for t, v in changes:
        if since is None and v == 0.0 and t0 < t < t1:
            since = t
        elif since is not None and v != 0.0:
            total += min(t, t1) - since
            since = None
    return total + (t1 - since if since is not None else 0.0)


def one_round(work: Path, cars: list[str], frames: Path, fault: str) -> list[dict]:
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
    if fault == "kill":
        primary.p.send_signal(signal.SIGKILL)
        primary.stop()
        time.sleep(3.0)
        t_back = time.monotonic()
        primary = fleet.server(fleet.files.server_config)
    else:
        primary.p.send_signal(signal.SIGSTOP)
        time.sleep(4.0)
        t_back = time.monotonic()
        primary.p.send_signal(signal.SIGCONT)
    time.sleep(6.0)  # the primary starts (~1-2 s) or resumes, takes its cars back, drives
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
                "stopped_ms": 1e3 * stopped_s(r["throttle_changes"], t_all, t_end),
                "commands_both_alive": len(both),
                "duplicates": r["counters"]["duplicates"],
            }
        )
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cars", type=int, default=4, help="car processes (default 4)")
    ap.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    ap.add_argument("--fault", choices=("kill", "freeze"), default="kill", help="SIGKILL or SIGSTOP of the primary")
    args = ap.parse_args()
    cars = [f"car{i + 1}" for i in range(args.cars)]
    with tempfile.TemporaryDirectory() as tmp:
        frames = Path(tmp) / "frames.npy"
        record_sim_frames(str(frames), count=12)
        for k in range(args.rounds):
            rows = one_round(Path(tmp) / f"r{k}", cars, frames, args.fault)
            for row in rows:
                print(
                    f"round {k + 1} {row['car']}: longest gap at the {args.fault} {row['gap_kill_ms']:.0f} ms,"
                    f" at the hand-back {row['gap_back_ms']:.0f} ms; stopped by its failsafe"
                    f" {row['stopped_ms']:.0f} ms; duplicates {row['duplicates']} (commands while the primary"
                    f" answered: {row['commands_both_alive']})",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
