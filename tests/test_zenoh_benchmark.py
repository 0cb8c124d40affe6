"""``benchmarks/zenoh.py`` runs its car->pilot->car trips end to end in a few seconds (tiny rounds) and its JSON has
the shape ``benchmarks/run_all.py`` turns into the zenoh rows of docs/benchmarks.md. The figures themselves are the
benchmark's business: a tiny run on a shared machine proves nothing about them."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"
ROUNDS, TRIPS = 2, 10
NAMES = {"frame raw", "frame JPEG", "scalar"}

pytestmark = [pytest.mark.realtime, pytest.mark.network, pytest.mark.subprocess]  # real trips, timed


def _run_all():
    sys.path.insert(0, str(BENCH))  # run_all imports machine_info beside it
    try:
        spec = importlib.util.spec_from_file_location("_bench_run_all", BENCH / "run_all.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCH))
    return mod


@pytest.fixture(scope="module")
def figures() -> dict:
    cmd = [sys.executable, str(BENCH / "zenoh.py"), "--json", "--quick", "--trips-only"]
    cmd += [f"--rounds={ROUNDS}", f"--trips={TRIPS}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=BENCH.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


def test_every_trip_runs_both_ways_every_round(figures: dict) -> None:
    trip = figures["trip"]
    assert trip["method"]["shared_memory"] is False
    for mode in ("two_process", "one_process"):
        t = trip[mode]
        assert t["rounds"] == ROUNDS and t["trips_per_round"] == TRIPS, mode
        assert set(t["trips"]) == NAMES, mode
        assert min(t["load"]["busy_pct"], t["load"]["benchmark_busy_pct"]) >= 0, mode
        for name, row in t["trips"].items():
            assert row["bytes_out"] > 0 and row["bytes_back"] > 0, name
            for who in ("ours", "raw"):
                r = row[who]
                assert r["n"] == ROUNDS * TRIPS, (mode, name, who)
                assert 0 < r["p50_ms"] <= r["p90_ms"] <= r["p99_ms"] <= r["max_ms"], (mode, name, who)
                assert len(r["p50_ms_rounds"]) == ROUNDS, (mode, name, who)
            ratio = row["ours_over_raw"]
            assert ratio["p50_min"] <= ratio["p50"] <= ratio["p50_max"], (mode, name)
    sizes = {name: row["bytes_out"] for name, row in trip["two_process"]["trips"].items()}
    assert sizes["frame raw"] == 120 * 160 * 3 and sizes["scalar"] < sizes["frame JPEG"] < sizes["frame raw"]


def test_run_all_makes_rows_of_them(figures: dict) -> None:
    rows = _run_all().zenoh_rows(figures)
    trips = [r for r in rows if "car→pilot→car trip" in r[1]]
    assert len(trips) == 2 * len(NAMES)
    for _bench, figure, ours, _theirs, _ratio in trips:
        assert "n/a" not in figure and "n/a" not in ours, figure
        assert len(ours.split(" / ")) == 3
