"""Run every benchmark and print one results table; ``--write-docs`` also puts it into docs/benchmarks.md.

    python benchmarks/run_all.py                  # full runs (about ten minutes with Donkeycar installed)
    python benchmarks/run_all.py --quick          # short runs, for a look
    python benchmarks/run_all.py --write-docs     # `make bench`: full runs, docs/benchmarks.md table and results JSON
    python benchmarks/run_all.py --only safety --write-docs   # rerun one; the others keep their saved figures

Each benchmark runs in its own process with ``--json`` (so one cannot warm up or disturb another), one after
the other (they are timing benchmarks: running them side by side on two cores would measure each other). The
table shows asyncdonkey beside the installed Donkeycar (5.3 on Python 3.11, 5.4 on 3.12-3.13), and the ratio
in the direction "how many times better": Donkeycar's figure over ours for times and errors, ours over
Donkeycar's for rates.
The table in docs/benchmarks.md is replaced between its ``benchmarks:begin`` / ``benchmarks:end`` markers, with
the machine it ran on and its load average at the start (figures from a busy machine are worse, and say so).
``--write-readme`` is the former name of ``--write-docs`` and does the same.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from machine_info import describe, donkeycar_version

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DOC = ROOT / "docs" / "benchmarks.md"
RESULTS = HERE / "results" / "latest.json"
BEGIN, END = "<!-- benchmarks:begin -->", "<!-- benchmarks:end -->"

Row = tuple[str, str, str, str, str]  # benchmark, figure, asyncdonkey, Donkeycar, ratio


def run_benchmark(name: str, quick: bool) -> dict[str, Any]:
    """``python benchmarks/<name>.py --json [--quick]`` in a fresh process; its JSON output."""
    cmd = [sys.executable, str(HERE / f"{name}.py"), "--json", *(["--quick"] if quick else [])]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"run_all: {name}.py failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    out = proc.stdout
    try:
        data = json.loads(out[out.index("{") :])  # tolerate a banner before the JSON
    except ValueError:
        raise SystemExit(f"run_all: {name}.py printed no JSON:\n{out[-2000:]}") from None
    print(f"  {name}.py: {time.monotonic() - t0:.0f} s", file=sys.stderr)
    return data


def _get(d: Any, *path: str) -> Any:
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def _fmt(x: Any, digits: int = 2) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, float) and abs(x) >= 1000:
        return f"{x:,.0f}"
    return f"{x:.{digits}f}" if isinstance(x, float) else str(x)


def _ratio(ours: Any, theirs: Any, higher_is_better: bool = False, floor: float = 0.0) -> str:
    """How many times better ours is. Below ``floor`` (the resolution of the figure) ours counts as the
    floor and the ratio is a bound ("> Nx"): dividing by a measured 0.3 ppm would be noise, not a result."""
    if ours is None or theirs is None:
        return "n/a"
    if higher_is_better:
        return _times(ours / theirs) if theirs else "n/a"
    a, b = abs(ours), abs(theirs)
    if a < floor:
        return f"> {_times(b / floor)}"
    return _times(b / a) if a else "n/a"


def _times(r: float) -> str:
    return f"{r:,.0f}x" if r >= 10 else f"{r:.1f}x"


def _cpu_cells(
    ours: dict[str, Any], dk: dict[str, Any], key: str = "cpu_pct", digits: int = 2, ratio: bool = True
) -> tuple[str, str, str]:
    """Ours, Donkeycar's and the ratio for a CPU figure measured over interleaved rounds: each side's median
    with its min-max, and the median of the per-round ratio (Donkeycar's over ours, "better by") with its
    min-max. Figures saved before the rounds existed (one run each) show as plain numbers."""

    def cell(r: dict[str, Any]) -> str:
        med, lo, hi = r.get(key), r.get(f"{key}_min"), r.get(f"{key}_max")
        if med is None or lo is None or hi is None:
            return _fmt(med, digits)
        return f"{_fmt(med, digits)} ({_fmt(lo, digits)}-{_fmt(hi, digits)})"

    a, b = ours.get(f"{key}_rounds"), dk.get(f"{key}_rounds")
    if not ratio:
        shown = ""
    elif a and b and len(a) == len(b):
        per_round = sorted(t / o for o, t in zip(a, b, strict=True) if o > 0)
        shown = f"{statistics.median(per_round):.2f}x ({per_round[0]:.2f}-{per_round[-1]:.2f})"
    else:
        shown = _ratio(ours.get(key), dk.get(key))
    return cell(ours), cell(dk) if dk else "n/a", shown


def _late_cell(r: dict[str, Any]) -> str:
    """The lateness p99 pooled over every segment and, in brackets, the median of each round's own p99: a
    segment caught in a stall of the shared machine moves the first, not the second."""
    pooled, per_round = r.get("lateness_p99_ms"), r.get("lateness_p99_ms_median_of_rounds")
    return _fmt(pooled, 3) + (f" (per-round median {_fmt(per_round, 3)})" if per_round is not None else "")


def loop_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    rounds = _get(d, "method", "rounds")
    over = f"; median (min-max) of {rounds} rounds" if rounds else ""
    for rate in ("20", "100", "1000"):
        ours, dk = _get(d, "rates", rate, "ours") or {}, _get(d, "rates", rate, "donkeycar") or {}
        precise = _get(d, "rates", rate, "ours_precise") or {}
        floor = _get(d, "rates", rate, "floor") or {}
        name = f"loop {rate} Hz"
        o, t = ours.get("rate_error_ppm"), dk.get("rate_error_ppm")
        # below twice the fit's standard error (and below 1 ppm in any case) is below what the run resolves
        res = float(max(1, math.ceil(2 * (ours.get("rate_error_se_ppm") or 0.0))))
        shown = f"< {_fmt(res, 0)}" if o is not None and abs(o) < res else _fmt(o, 0)
        skipped = ours.get("rate_error_skipped_deadlines")
        if skipped:  # the machine (or the loop) stalled past a period: the rate error is those deadlines
            shown += f" ({skipped} skipped)"
        rows.append((name, "rate error (ppm)", shown, _fmt(t, 0), _ratio(o, t, floor=res)))
        o, t = ours.get("lateness_p99_ms"), dk.get("lateness_p99_ms")
        fl = f"; bare time.sleep loop {_fmt(floor.get('lateness_p99_ms'), 3)}" if floor else ""
        rows.append((name, f"tick lateness p99 (ms{fl})", _late_cell(ours), _fmt(t, 3), _ratio(o, t)))
        rows.append((name, f"CPU (% of a core{over})", *_cpu_cells(ours, dk)))
        if "cpu_us_per_tick" in ours:
            fl = f"; bare time.sleep loop {_fmt(floor.get('cpu_us_per_tick'), 0)}" if floor else ""
            rows.append((name, f"CPU per tick (µs{fl})", *_cpu_cells(ours, dk, "cpu_us_per_tick", 0, ratio=False)))
        if precise:
            o = precise.get("lateness_p99_ms")
            rows.append((name, "precise: tick lateness p99 (ms)", _late_cell(precise), _fmt(t, 3), _ratio(o, t)))
            spin = precise.get("spin_window_ms")
            spun = f"; spin window {_fmt(spin, 3)} ms" if spin is not None else ""
            if spin is not None and "two_sleeps" in precise:  # (figures saved before precise mode could sleep twice)
                spun += f", two sleeps in {precise['two_sleeps']} of {len(precise['spin_window_ms_rounds'])} rounds"
            rows.append((name, f"precise: CPU (% of a core{over}{spun})", *_cpu_cells(precise, dk)))
    idle = d.get("idle") or {}
    ours, dk, floor = idle.get("ours"), idle.get("donkeycar") or {}, idle.get("floor") or {}
    name = f"loop {_get(d, 'method', 'idle_hz') or 20} Hz, no poller"
    if ours:
        rows.append((name, f"idle CPU (% of a core{over})", *_cpu_cells(ours, dk)))
        fl = f"; bare time.sleep loop {_fmt(floor.get('cpu_us_per_tick'), 0)}" if floor else ""
        rows.append((name, f"idle CPU per tick (µs{fl})", *_cpu_cells(ours, dk, "cpu_us_per_tick", 0, ratio=False)))
    else:  # figures saved before the rounds existed
        o, t = _get(d, "idle_cpu_pct", "ours"), _get(d, "idle_cpu_pct", "donkeycar")
        rows.append((name, "idle CPU (% of a core)", _fmt(o), _fmt(t), _ratio(o, t)))
    o, t = _get(d, "overhead_us", "ours"), _get(d, "overhead_us", "donkeycar")
    rows.append(("loop", "per-part overhead (µs)", _fmt(o), _fmt(t), _ratio(o, t)))
    return rows


def tub_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    for key, label in (("p50_ms", "p50"), ("p99_ms", "p99"), ("max_ms", "max")):
        o, t = _get(d, "ours", "20hz", key), _get(d, "donkeycar", "20hz", key)
        rows.append(("tub 20 Hz", f"in-loop cost {label} (ms)", _fmt(o, 3), _fmt(t, 3), _ratio(o, t)))
    o, t = _get(d, "ours", "drain", "records_per_s"), _get(d, "donkeycar", "flat", "records_per_s")
    rows.append(("tub", "sustained records/s", _fmt(o, 0), _fmt(t, 0), _ratio(o, t, higher_is_better=True)))
    return rows


def pilot_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    for m in d.get("models", []):
        for f in m.get("forms", []):
            name = f"pilot: {m.get('model', '?')}, {f.get('form', '?')}"
            if "missing" in f:
                rows.append((name, "predict p50 / p99 (ms)", "n/a (model not built)", "", ""))
                continue
            p50, p99 = _get(f, "predict", "p50_ms"), _get(f, "predict", "p99_ms")
            over = f.get("predict_overhead_pct")
            shown = f"{_fmt(p50, 3)} / {_fmt(p99, 3)} ({over:+.1f} %)" if over is not None else "n/a"
            rows.append((name, "predict p50 / p99 (ms) (overhead vs bare runtime)", shown, "", ""))
            mae, diff = f.get("replay_angle_mae"), f.get("angle_diff_vs_float32")
            rows.append(
                (name, "replay angle MAE (mean abs diff vs float32)", f"{_fmt(mae, 4)} ({_fmt(diff, 4)})", "", "")
            )
    return rows


def safety_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    for kind in ("sleeping", "spinning"):
        w = _get(d, "watchdog", kind) or {}
        rows.append(
            (
                f"watchdog, loop blocked ({kind})",
                "neutral after the stale deadline, max (ms)",
                _fmt(w.get("after_deadline_max_ms"), 1),
                "never",
                "",
            )
        )
    for key, label in (("kill9_to_safe", "after kill -9"), ("gil_held_since_hang", "GIL held, since the hang")):
        rows.append(
            (
                f"safety process, {label}",
                "safe state, max (ms)",
                _fmt(_get(d, "safety_process", key, "max_ms"), 1),
                "never",
                "",
            )
        )
    rows.append(
        ("safety process", "heartbeat per tick (ns)", _fmt(_get(d, "safety_process", "heartbeat_ns"), 0), "", "")
    )
    o = _get(d, "provenance", "one_input", "added_ns")
    rows.append(("provenance", "added per part output (ns)", _fmt(o, 0), "", ""))
    o, t = _get(d, "overhead", "ours_us"), _get(d, "overhead", "donkeycar_us")
    rows.append(("provenance", "per-part overhead incl. origins (µs)", _fmt(o), _fmt(t), _ratio(o, t)))
    s = d.get("sim_car") or {}
    for key, label in (("p50_ms", "p50"), ("p99_ms", "p99")):
        rows.append(("simulated car 20 Hz", f"sensing-to-actuation {label} (ms)", _fmt(s.get(key), 1), "n/a", ""))
    return rows


def control_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    for r in d.get("virtual", []):
        if r.get("inference_ms") != 80.0:
            continue
        label = f"seed car, 80 ms pilot, {r['mode']}"
        rows.append((label, "loop rate (Hz)", _fmt(r.get("loop_hz")), "", ""))
        rows.append((label, "sensing-to-actuation p50 (ms)", _fmt(r.get("latency_p50_ms"), 0), "", ""))
    for mode, r in (_get(d, "real", "modes") or {}).items():
        label = f"real loop, ~40 ms OnnxPilot, {mode}"
        rows.append((label, "loop rate (Hz) / overruns", f"{_fmt(r.get('loop_hz'))} / {r.get('overruns')}", "", ""))
    return rows


def mcap_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    for key, label in (("mcap_in_loop_20hz", "McapRecorder"), ("tub_in_loop_20hz", "TubWriter")):
        for q in ("p50_ms", "p99_ms"):
            rows.append((f"recording 20 Hz, {label}", f"in-loop cost {q[:3]} (ms)", _fmt(_get(d, key, q), 3), "", ""))
    rows.append(
        (
            "recording, McapRecorder",
            "ticks/s written flat out",
            _fmt(_get(d, "mcap_flat_out", "ticks_per_s"), 0),
            "",
            "",
        )
    )
    return rows


def web_rows(d: dict[str, Any]) -> list[Row]:
    rows: list[Row] = []
    for key, label in (("latency_p50_ms", "p50"), ("latency_p99_ms", "p99")):
        o, t = _get(d, "ours", "0", key), _get(d, "donkeycar", "0", key)
        rows.append(("web", f"WebSocket command to Memory {label} (ms)", _fmt(o, 1), _fmt(t, 1), _ratio(o, t)))
    for key, label in (("to_pwm_p50_ms", "p50"), ("to_pwm_p99_ms", "p99")):
        o = _get(d, "ours", "0", key)
        rows.append(("web", f"command arrival to PWM write {label} (ms)", _fmt(o, 1), "n/a", ""))
    for n in ("0", "1", "3"):
        name = f"web, {n} video viewer{'' if n == '1' else 's'}"
        o, t = _get(d, "ours", n, "cpu_pct"), _get(d, "donkeycar", n, "cpu_pct")
        rows.append((name, "car process CPU (% of a core)", _fmt(o, 1), _fmt(t, 1), _ratio(o, t)))
        o, t = _get(d, "ours", n, "lateness_p99_ms"), _get(d, "donkeycar", n, "lateness_p99_ms")
        rows.append((name, "tick lateness p99 (ms)", _fmt(o, 3), _fmt(t, 3), _ratio(o, t)))
    return rows


def virtual_clock_rows(d: dict[str, Any]) -> list[Row]:
    ticks = f"{d.get('ticks', 10_000):,} ticks"
    figures = (
        (" of a 10-part 20 Hz car", "car_s"),
        (", the loop alone: a task awaiting a timer", "loop_s"),
        (", the loop alone: asyncio.sleep", "sleep_loop_s"),
        (", the loop alone: call_at chain", "call_at_chain_s"),
        (", the loop alone: a timer queueing a callback", "timer_call_soon_chain_s"),
        (", plain asyncio without timers", "plain_asyncio_s"),
        (", plain asyncio call_soon chain", "plain_call_soon_chain_s"),
    )
    return [("virtual clock", f"{ticks}{what} (s)", _fmt(d.get(key), 3), "", "") for what, key in figures]


def _bytes(n: Any) -> str:
    return f"{n:,}" if isinstance(n, int) else "n/a"


def zenoh_rows(d: dict[str, Any]) -> list[Row]:
    """Channels over Zenoh: our figure, with raw Zenoh's (the floor) in the figure's name; no Donkeycar column.

    The trip is the off-board pilot's: car -> pilot -> car through the parts, against the same trip in raw Zenoh
    on the same sessions; figures saved before it (``round_trip``: one send and one receive through an echo)
    show as what they were."""
    rows: list[Row] = []
    trip = d.get("trip") or {}
    for mode, where in (("two_process", "pilot in another process"), ("one_process", "pilot in the car's process")):
        t = trip.get(mode) or {}
        load = t.get("load") or {}
        for name, r in (t.get("trips") or {}).items():
            ours, raw, ratio = r.get("ours") or {}, r.get("raw") or {}, r.get("ours_over_raw") or {}
            q = ("p50_ms", "p90_ms", "p99_ms")
            times = ", ".join(f"{_fmt(ratio.get(k[:3]))}x" for k in q)
            figure = (
                f"car→pilot→car trip p50 / p90 / p99 (ms; raw Zenoh {' / '.join(_fmt(raw.get(k), 3) for k in q)};"
                f" ours/raw {times}; {_bytes(r.get('bytes_out'))} B out, {_bytes(r.get('bytes_back'))} B back;"
                f" medians of {t.get('rounds')} rounds of {t.get('trips_per_round')})"
            )
            rows.append((f"zenoh {name}, {where}", figure, " / ".join(_fmt(ours.get(k), 3) for k in q), "", ""))
        if load:
            rows.append(
                (
                    f"zenoh trips, {where}",
                    "machine CPU busy during the trips (% of all cores; of it the car and pilot processes)",
                    f"{_fmt(load.get('busy_pct'), 0)} ({_fmt(load.get('benchmark_busy_pct'), 0)})",
                    "",
                    "",
                )
            )
    for name, r in (d.get("round_trip") or {}).items():  # figures saved before the car->pilot->car trip
        floor = _fmt(_get(r, "raw", "p50_ms"), 3)
        rows.append(
            (
                f"zenoh {name}",
                f"one send + one receive through an echo p50 (ms; raw Zenoh {floor})",
                _fmt(_get(r, "channel", "p50_ms"), 3),
                "",
                "",
            )
        )
    for name, r in (d.get("throughput") or {}).items():
        floor = _fmt(_get(r, "raw", "received_per_s"), 0)
        rows.append(
            (
                f"zenoh {name}",
                f"received/s flat out (raw Zenoh {floor})",
                _fmt(_get(r, "channel", "received_per_s"), 0),
                "",
                "",
            )
        )
    ticks = d.get("ticks_20hz") or {}
    base = _fmt(_get(ticks, "no publishing", "lateness_p99_ms"), 3)
    for name in ("frame raw", "frame JPEG"):
        r = ticks.get(name) or {}
        rows.append(
            (
                f"zenoh 20 Hz, {name}",
                f"tick lateness p99 (ms; not publishing {base})",
                _fmt(r.get("lateness_p99_ms"), 3),
                "",
                "",
            )
        )
        rows.append((f"zenoh 20 Hz, {name}", "added CPU (ms per s)", _fmt(r.get("added_cpu_ms_per_s"), 1), "", ""))
        pub = _get(r, "publisher", "p50_ms")
        if pub is not None:
            rows.append((f"zenoh 20 Hz, {name}", "publisher time per tick p50 (ms)", _fmt(pub, 3), "", ""))
    return rows


def wake_rows(d: dict[str, Any]) -> list[Row]:
    """One wake-up's CPU: the drive loop's wait (an asyncdonkey waiter on uvloop) beside a thread's sleep (how
    Donkeycar waits), the other ways of waiting in the figure's name."""
    us = d.get("us_per_wake") or {}
    if not us:
        return []
    others = [("bare uvloop", "uvloop"), ("Python epoll", "epoll"), ("timerfd read", "timerfd read")]
    others.append(("asyncio's loop", "asyncio"))
    named = ", ".join(f"{label} {_fmt(us.get(key), 0)}" for label, key in others)
    o, t = us.get("asyncdonkey waiter"), us.get("sleep")
    rate = _fmt(d.get("rate_hz"), 0)
    figure = f"CPU per wake-up, doing nothing (µs; theirs: a thread's time.sleep, as Donkeycar waits; {named})"
    return [(f"wake-up {rate} Hz", figure, _fmt(o, 0), _fmt(t, 0), _ratio(o, t))]


def fleet_rows(d: dict[str, Any]) -> list[Row]:
    """A fleet on one pilot server (benchmarks/fleet.py): per car count, batched and one call per frame."""
    rows: list[Row] = []
    figure = "frame→command p50 / p99 (ms); server CPU (% of a core); mean batch"
    for mode, runs in (d.get("runs") or {}).items():
        for r in runs:
            cell = (
                f"{_fmt(r.get('latency_p50_ms'), 1)} / {_fmt(r.get('latency_p99_ms'), 1)};"
                f" {_fmt(r.get('server_cpu_pct'), 0)} %; {_fmt(r.get('batch_mean'), 1)}"
                + (" (saturated)" if r.get("saturated") else "")
            )
            rows.append((f"fleet {r.get('cars')} cars, {mode.replace('_', ' ')}", figure, cell, "", ""))
    sat = d.get("saturates_at") or {}
    if sat:
        beyond = "beyond the counts run"
        shown = ", ".join(f"{m.replace('_', ' ')} {v if v is not None else beyond}" for m, v in sat.items())
        rows.append(("fleet", "car count at which the server saturates", shown, "", ""))
    return rows


BENCHMARKS: dict[str, Callable[[dict[str, Any]], list[Row]]] = {
    "loop": loop_rows,
    "wake": wake_rows,
    "tub": tub_rows,
    "pilot": pilot_rows,
    "safety": safety_rows,
    "control_periods": control_rows,
    "mcap_recorder": mcap_rows,
    "web": web_rows,
    "virtual_clock": virtual_clock_rows,
    "zenoh": zenoh_rows,
    "fleet": fleet_rows,
}


def markdown(rows: list[Row], where: str, when: str, quick: bool, donkeycar: str | None = None) -> str:
    theirs = f"Donkeycar {'.'.join(donkeycar.split('.')[:2])}" if donkeycar else "Donkeycar"
    lines = [
        f"Measured {when} on {where}{' (quick runs)' if quick else ''} by `make bench`.",
        "",
        f"| benchmark | figure | asyncdonkey | {theirs} | better by |",
        "|---|---|---:|---:|---:|",
    ]
    lines += [f"| {b} | {f} | {o} | {t} | {r} |" for b, f, o, t, r in rows]
    return "\n".join(lines)


def write_doc(table: str, path: Path = DOC) -> None:
    """Replace the table between the markers in ``path`` (docs/benchmarks.md); without markers, append it."""
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    block = f"{BEGIN}\n{table}\n{END}"
    if BEGIN in text and END in text:
        text = re.sub(re.escape(BEGIN) + r".*?" + re.escape(END), lambda _m: block, text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n## The latest run\n\n" + block + "\n"
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="short runs of each benchmark")
    ap.add_argument(
        "--write-docs",
        "--write-readme",  # its former name, when the table lived in the README
        dest="write_docs",
        action="store_true",
        help=f"replace the results table in {DOC.relative_to(ROOT)} and save the figures",
    )
    ap.add_argument("--only", choices=sorted(BENCHMARKS), action="append", help="run only these benchmarks")
    ap.add_argument(
        "--from-json", type=Path, metavar="FILE", help=f"no runs: rebuild the table from saved figures ({RESULTS.name})"
    )
    args = ap.parse_args(argv)

    if args.from_json:
        results = json.loads(args.from_json.read_text())
        where, when, quick = results["machine"], results["date"], results.get("quick", False)
    else:
        where, when, quick = describe(with_load=True), dt.date.today().isoformat(), args.quick
        print(f"benchmarks on {where}", file=sys.stderr)
        results = {"machine": where, "date": when, "quick": quick, "donkeycar": donkeycar_version()}
        if args.only and RESULTS.exists():
            # a partial run updates the saved figures: the other benchmarks keep theirs
            saved = json.loads(RESULTS.read_text())
            results = {**saved, **results, "quick": quick or saved.get("quick", False)}
        for name in BENCHMARKS:
            if not args.only or name in args.only:
                results[name] = run_benchmark(name, quick)
    rows: list[Row] = []
    for name, to_rows in BENCHMARKS.items():
        if name in results:
            rows += to_rows(results[name])
    # saved figures from before the version was recorded were measured against Donkeycar 5.3.0
    table = markdown(rows, where, when, quick, results.get("donkeycar", "5.3.0"))
    print(table)
    if args.write_docs:
        write_doc(table)
        if not args.from_json:
            RESULTS.parent.mkdir(exist_ok=True)
            RESULTS.write_text(json.dumps(results, indent=2) + "\n")
        where_to = f"{DOC.relative_to(ROOT)} and the figures into {RESULTS.relative_to(ROOT)}"
        print(f"wrote the table into {where_to}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
