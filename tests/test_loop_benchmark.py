"""``benchmarks/loop.py`` runs end to end in a few seconds (tiny rounds) and its JSON has the shape
``benchmarks/run_all.py`` turns into the docs/benchmarks.md table: every configuration of every round, medians inside
their spreads, per-round ratios to Donkeycar. The figures themselves are the benchmark's business, not the
test's: a tiny run on a shared machine proves nothing about them."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = [pytest.mark.realtime]

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"
ROUNDS = 2


def _module(name: str):
    sys.path.insert(0, str(BENCH))  # the benchmarks import machine_info beside them
    try:
        spec = importlib.util.spec_from_file_location(f"_bench_{name}", BENCH / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(BENCH))
    return mod


@pytest.fixture(scope="module")
def figures() -> dict:
    cmd = [sys.executable, str(BENCH / "loop.py"), "--json", f"--rounds={ROUNDS}", "--segment-s=0.05"]
    cmd += ["--ticks=8", "--overhead-ticks=100", "--overhead-repeats=2"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=BENCH.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


@pytest.mark.donkeycar
@pytest.mark.subprocess
def test_every_configuration_runs_every_round(figures: dict) -> None:
    rates = figures["rates"]
    assert sorted(rates, key=int) == ["20", "100", "1000"]
    for rate, row in rates.items():
        expected = {"ours", "donkeycar", "floor"} | ({"ours_precise"} if rate != "1000" else set())
        assert set(row) == expected, rate
    assert set(figures["idle"]) == {"ours", "donkeycar", "floor"}
    for row in [*rates.values(), figures["idle"]]:
        for who, r in row.items():
            assert len(r["cpu_pct_rounds"]) == ROUNDS, who
            assert r["cpu_pct_min"] <= r["cpu_pct"] <= r["cpu_pct_max"], who
            assert r["cpu_us_per_tick_min"] <= r["cpu_us_per_tick"] <= r["cpu_us_per_tick_max"], who
            assert r["cpu_pct"] > 0 and r["cpu_us_per_tick"] > 0, who
            assert r["lateness_p50_ms"] <= r["lateness_p99_ms"] <= r["lateness_max_ms"], who
            if who == "donkeycar":  # no deadlines: its lateness is its drift, from the long run
                assert "lateness_p99_ms_rounds" not in r
            else:
                assert len(r["lateness_p99_ms_rounds"]) == ROUNDS, who
                assert r["lateness_p99_ms_median_of_rounds"] <= r["lateness_max_ms"], who


@pytest.mark.donkeycar
@pytest.mark.subprocess
def test_ratios_are_per_round(figures: dict) -> None:
    for row in [*figures["rates"].values(), figures["idle"]]:
        dk = row["donkeycar"]["cpu_pct_rounds"]
        for who in ("ours", "ours_precise"):
            if who not in row:
                continue
            r = row[who]
            assert r["cpu_ratio_rounds"] == pytest.approx([a / b for a, b in zip(r["cpu_pct_rounds"], dk, strict=True)])
            assert r["cpu_ratio_min"] <= r["cpu_ratio"] <= r["cpu_ratio_max"]
        assert "cpu_ratio" not in row["floor"] and "cpu_ratio" not in row["donkeycar"]


@pytest.mark.donkeycar
@pytest.mark.subprocess
def test_timing_comes_from_the_long_runs(figures: dict) -> None:
    # the first round runs the cars for --ticks (x5 at 1 kHz): the rate error's run; Donkeycar's lateness
    # (which grows with its drift) comes from it alone, ours is pooled over every segment
    assert figures["rates"]["20"]["ours"]["rate_error_ticks"] == 8
    assert figures["rates"]["100"]["ours_precise"]["rate_error_ticks"] == 8
    assert figures["rates"]["1000"]["donkeycar"]["rate_error_ticks"] == 40
    assert figures["rates"]["20"]["donkeycar"]["lateness_ticks"] == 8
    assert figures["rates"]["20"]["ours"]["lateness_ticks"] > 8
    assert figures["overhead_us"]["ratio"] == pytest.approx(
        figures["overhead_us"]["ours"] / figures["overhead_us"]["donkeycar"]
    )


@pytest.mark.donkeycar
@pytest.mark.subprocess
def test_run_all_builds_the_readme_rows(figures: dict) -> None:
    run_all = _module("run_all")
    rows = run_all.loop_rows(figures)
    by_figure = {(b, f): (o, t, r) for b, f, o, t, r in rows}
    ours, dk, ratio = by_figure[("loop 100 Hz", f"CPU (% of a core; median (min-max) of {ROUNDS} rounds)")]
    assert ours.startswith(f"{figures['rates']['100']['ours']['cpu_pct']:.2f} (") and dk.endswith(")")
    assert ratio.endswith(")") and "x (" in ratio
    floor = figures["rates"]["100"]["floor"]
    per_tick = by_figure[("loop 100 Hz", f"CPU per tick (µs; bare time.sleep loop {floor['cpu_us_per_tick']:.0f})")]
    assert per_tick[2] == ""  # the ratio is the CPU row's: same ticks, same wall time
    late = by_figure[("loop 100 Hz", f"tick lateness p99 (ms; bare time.sleep loop {floor['lateness_p99_ms']:.3f})")]
    ours = figures["rates"]["100"]["ours"]
    assert late[0] == f"{ours['lateness_p99_ms']:.3f} (per-round median {ours['lateness_p99_ms_median_of_rounds']:.3f})"
    floor = figures["idle"]["floor"]["cpu_us_per_tick"]
    assert ("loop 20 Hz, no poller", f"idle CPU per tick (µs; bare time.sleep loop {floor:.0f})") in by_figure
    # precise mode's CPU row names the spin window it learned (the default mode has none)
    precise = figures["rates"]["100"]["ours_precise"]
    assert len(precise["spin_window_ms_rounds"]) == ROUNDS and "spin_window_ms" not in figures["rates"]["100"]["ours"]
    assert 0 <= precise["two_sleeps"] <= ROUNDS
    window = f"spin window {precise['spin_window_ms']:.3f} ms, two sleeps in {precise['two_sleeps']} of {ROUNDS} rounds"
    spun = f"precise: CPU (% of a core; median (min-max) of {ROUNDS} rounds; {window})"
    assert by_figure[("loop 100 Hz", spun)][0].startswith(f"{precise['cpu_pct']:.2f} (")
    table = run_all.markdown(rows, "test machine", "today", quick=True)
    assert table.count("| loop") == len(rows)


@pytest.mark.donkeycar
@pytest.mark.subprocess
def test_run_all_names_the_skipped_deadlines_behind_a_rate_error(figures: dict) -> None:
    run_all = _module("run_all")
    stalled = json.loads(json.dumps(figures))
    stalled["rates"]["100"]["ours"].update(
        rate_error_ppm=-3000.0, rate_error_se_ppm=20.0, rate_error_skipped_deadlines=3
    )
    rows = {(b, f): o for b, f, o, _t, _r in run_all.loop_rows(stalled)}
    assert rows[("loop 100 Hz", "rate error (ppm)")] == "-3,000 (3 skipped)"
    # below twice its standard error a rate error is not resolved: it shows as a bound
    stalled["rates"]["100"]["ours"].update(rate_error_ppm=-30.0, rate_error_se_ppm=20.0, rate_error_skipped_deadlines=0)
    rows = {(b, f): o for b, f, o, _t, _r in run_all.loop_rows(stalled)}
    assert rows[("loop 100 Hz", "rate error (ppm)")] == "< 40"


@pytest.mark.donkeycar
def test_the_safety_benchmark_takes_its_per_part_overhead_from_the_loop_benchmark():
    """benchmarks/safety.py reuses the loop benchmark's measure: a rename there must not break it silently."""
    out = _module("safety").loop_overhead(300)
    assert out["ours_us"] > 0
    assert out["donkeycar_us"] > 0  # make test installs Donkeycar


@pytest.mark.subprocess
def test_the_wake_benchmark_measures_every_way_of_waiting_and_makes_its_readme_row():
    """``benchmarks/wake.py`` end to end in a second (tiny repetitions): every way of waiting woke and cost
    something, and run_all names them all in one row beside a thread's sleep."""
    cmd = [sys.executable, str(BENCH / "wake.py"), "--json", "--rate=100", "--reps=2", "--seconds=0.1"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=BENCH.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    figures = json.loads(proc.stdout)
    ways = {"sleep", "timerfd read", "epoll", "uvloop", "asyncio", "asyncdonkey waiter"}
    assert set(figures["us_per_wake"]) == ways == set(figures["us_per_wake_runs"])
    for way, runs in figures["us_per_wake_runs"].items():
        assert len(runs) == 2 and all(us > 0 for us in runs), way
        assert min(runs) <= figures["us_per_wake"][way] <= max(runs), way
    ((bench, figure, ours, theirs, ratio),) = _module("run_all").wake_rows(figures)
    assert bench == "wake-up 100 Hz"
    assert ours == f"{figures['us_per_wake']['asyncdonkey waiter']:.0f}"
    assert theirs == f"{figures['us_per_wake']['sleep']:.0f}"
    assert f"bare uvloop {figures['us_per_wake']['uvloop']:.0f}" in figure and ratio.endswith("x")
