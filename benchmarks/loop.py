"""Drive-loop timing and CPU cost: rate error, tick lateness, CPU per wall second and per tick, per-part
overhead, beside Donkeycar's Vehicle and beside the cost of waking up at all.

The car: 10 trivial parts plus a 60 Hz hardware poller (ours: a ``Poller``; Donkeycar's: a threaded part that
reads and sleeps a period, as its IMU does), at 20, 100 and 1000 Hz. The loops measured, one *configuration*
each per rate: asyncdonkey in its default mode (timerfd waits, no spinning), asyncdonkey in precise mode
(``run(precise=True)``: the last stretch before each deadline is spun, with a learned window; 20 and 100 Hz),
Donkeycar's ``Vehicle`` (when ``donkeycar`` is importable) and the *floor*: a bare thread sleeping to the same
deadlines with ``time.sleep`` and stamping each wake as the car's first part does, which is what one wake-up
costs on this machine before any runtime runs. The *idle* group is the same 10 parts with no poller at 20 Hz
(ours, Donkeycar's, the floor): what a car whose parts do nothing costs.

CPU on a small shared VM moves by ±50 % over minutes (other processes, frequency, cache neighbours), far more
than the differences measured, so one run per configuration says little. Here every configuration runs as
several short *segments*, interleaved in *rounds*: round after round, each rate's configurations run one after
the other (their order rotated each round, so none always follows the same one). Per configuration the CPU is
the median over rounds with its min-max spread, and the ratio to Donkeycar is taken per round (ours over
Donkeycar's, run seconds apart) and its median reported: a slow minute slows both sides of a ratio. Within
one run the per-round ratios still spread from about 0.75 to 1.25 around their median, and the median of five
moved by as much from one run to the next, so a full run takes ten rounds of one second rather than five of
two: twice the ratios in the same time.

Running the two cars *concurrently* instead, in two processes over the same wall window, was tried and not
adopted. Over 12 rounds of 2.5 s at 20 and 100 Hz on the 2-core VM this was written on, the per-round ratio's
spread (standard deviation of its log) was 0.13 and 0.18 concurrent against 0.19 and 0.22 sequential, with the
same medians, but each car's own CPU read up to 15 % higher (each also pays for the other on the shared caches
and cores, so the figures would no longer be one car's alone); with both started on the same phase, waking
together every period, the ratio was steadier still (0.07 and 0.12) but 6 and 25 % higher. A modest gain, for
figures that no longer describe one car: the segments run one after another, in one process.

Figures, per configuration:
  * rate error in ppm: the slope of a least-squares line through the tick start times against the period
    asked for (the two endpoints alone would measure their own jitter, not the rate), from the first round,
    whose car segments (ours in both modes, Donkeycar's) are long runs (``--ticks``, x5 at 1 kHz); the floor
    and the idle group fit one slope through all their segments (one offset each). ``rate_error_se_ppm`` is the
    fit's standard error: a rate error below it is below what the run resolves. A deadline loop does not
    drift: its rate error is the deadlines it skipped when the machine stalled for more than a period,
    counted beside it,
  * tick lateness p50 / p99 / max in ms, pooled over all segments: tick start minus its deadline as the loop
    reports it (so a skipped deadline does not count as every later tick being late; the floor likewise);
    beside them the median over rounds of each segment's own p99, which one stalled segment cannot move.
    Donkeycar has no deadlines: its lateness is tick start minus ``t_first + k / rate_hz``, which grows with
    its drift and so with the run's length; it is taken from the long run only,
  * CPU % of one core: process CPU time (all threads: the loop, the poller, Donkeycar's threads) per wall
    second between a segment's first and last tick; median and min-max over rounds,
  * CPU µs per tick: the same CPU time over the ticks, the per-wake cost (the car's rows include the poller's
    60 wakes a second; the idle rows have none), beside the floor's,
  * the per-round ratio of CPU to Donkeycar's, median and min-max.
And per-part overhead in µs: the cost the loop adds around a trivial part, profiling on, measured flat out as
(tick time with 20 parts - tick time with none) / 20, each the minimum over interleaved repeats (the
machine's noise only ever adds time); a tick's time runs from the first tick's start to the last's, for both
cars, so a drive's start and end-of-drive report are not in it.

asyncdonkey runs on uvloop (as ``Vehicle.start`` does) unless ``--no-uvloop``; Donkeycar runs in the same
process.

    python benchmarks/loop.py            # 10 rounds of 1 s segments, 1,000-tick long runs (about 6 minutes)
    python benchmarks/loop.py --quick    # 3 rounds of 0.6 s segments, 100-tick long runs (about a minute)
    python benchmarks/loop.py --json     # figures as JSON for benchmarks/run_all.py
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np
from prettytable import PrettyTable

from asyncdonkey import Poller, Vehicle
from asyncdonkey.loop import run_blocking
from machine_info import describe, donkeycar_label

try:  # Donkeycar prints a banner on import; keep it out of the figures
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from donkeycar.vehicle import Vehicle as DonkeyVehicle
except ImportError:  # pragma: no cover - donkeycar is optional
    DonkeyVehicle = None

RATES = (20, 100, 1000)
PRECISE_RATES = (20, 100)
N_PARTS = 10
POLL_HZ = 60
IDLE_HZ = 20
IDLE = "idle"
MIN_SEGMENT_TICKS = 3
SETTLE_S = 0.1  # pause between segments (at most a quarter of one), after the previous one's threads ended
WHO = ("ours", "ours_precise", "donkeycar", "floor")
LABELS = {
    "ours": "asyncdonkey",
    "ours_precise": "asyncdonkey precise",
    "donkeycar": donkeycar_label(),
    "floor": "floor: time.sleep thread",
}
FULL = {"rounds": 10, "segment_s": 1.0, "ticks": 1000, "overhead_ticks": 10_000, "overhead_repeats": 7}
QUICK = {"rounds": 3, "segment_s": 0.6, "ticks": 100, "overhead_ticks": 3_000, "overhead_repeats": 3}


class Stamp:
    """First part of the graph: records when each tick started (time.monotonic, same for both loops) and the
    process CPU time then."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.cpu: list[float] = []

    def run(self) -> None:
        self.times.append(time.monotonic())
        self.cpu.append(time.process_time())


class Noop:
    def run(self, x=None):
        return x


def sensor_read() -> float:
    """The poller's "device": trivial, so the figures are the runtime's cost, not the read's."""
    return 0.5


class DonkeyStylePoller:
    """A sensor as Donkeycar's threaded parts poll one (its IMU, for one): read, sleep the period, repeat."""

    def __init__(self, rate_hz: float) -> None:
        self.period = 1.0 / rate_hz
        self.value = None
        self.on = True

    def update(self) -> None:
        while self.on:
            self.value = sensor_read()
            time.sleep(self.period)

    def run_threaded(self):
        return self.value

    def shutdown(self) -> None:
        self.on = False


def _graph(vehicle, n_parts: int, poller: str | None = None) -> Stamp:
    stamp = Stamp()
    vehicle.add(stamp)
    for i in range(n_parts):
        vehicle.add(Noop(), inputs=[f"c{i}"], outputs=[f"c{i + 1}"])
    if poller == "ours":
        vehicle.add(Poller(sensor_read, POLL_HZ, name="imu"), outputs=["imu"])
    elif poller == "donkeycar":
        vehicle.add(DonkeyStylePoller(POLL_HZ), outputs=["imu"], threaded=True)
    return stamp


# ------------------------------------------------------------------------------------------------ segments
@dataclass
class Segment:
    """One run of one configuration: its tick start times, the CPU time between its first and last tick and
    its ticks' lateness in seconds."""

    times: np.ndarray
    cpu_s: float
    lateness_s: np.ndarray
    long_run: bool = False
    skipped_deadlines: int = 0
    spin_window_ms: float | None = None  # precise mode's learned window at the segment's end
    precise_sleeps: int | None = None  # and how many times it slept before the spin (1 or 2)

    @classmethod
    def from_stamp(cls, stamp: Stamp, lateness_s: np.ndarray, **kw) -> Segment:
        if len(stamp.times) < 2:
            raise RuntimeError(f"loop benchmark: a segment ran {len(stamp.times)} tick(s), at least 2 are needed")
        return cls(np.asarray(stamp.times), stamp.cpu[-1] - stamp.cpu[0], np.asarray(lateness_s), **kw)

    @property
    def wall_s(self) -> float:
        return float(self.times[-1] - self.times[0])

    @property
    def cpu_pct(self) -> float:
        return self.cpu_s / self.wall_s * 100

    @property
    def us_per_tick(self) -> float:
        return self.cpu_s / (len(self.times) - 1) * 1e6


@dataclass(frozen=True)
class Config:
    group: str  # "20", "100", "1000" or "idle"
    who: str  # one of WHO
    rate_hz: float
    poller: bool


def _settle(pause_s: float = SETTLE_S) -> None:
    """Let the previous segment's threads finish, so they are not billed to the next one."""
    deadline = time.monotonic() + 2.0
    while threading.active_count() > 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(pause_s)


def ours_segment(rate_hz: float, ticks: int, use_uvloop: bool, precise: bool = False, poller: bool = True) -> Segment:
    v = Vehicle()
    stamp = _graph(v, N_PARTS, "ours" if poller else None)
    # bounded in time as well: a machine stalling for seconds makes the loop skip deadlines, and the segment
    # would otherwise run on until its ticks were done
    limit = ticks / rate_hz + 1.0
    report = run_blocking(v.run(rate_hz, ticks, duration=limit, precise=precise), use_uvloop=use_uvloop)
    # Lateness against each tick's own deadline, as the loop measures it: when a stall made the loop skip a
    # deadline, the ticks after it are due one period later, not "late by a period" from then on.
    late = v.profiler.lateness.recent(drop_last=False)
    return Segment.from_stamp(
        stamp,
        late,
        skipped_deadlines=report.skipped_deadlines,
        spin_window_ms=report.spin_window_ms,
        precise_sleeps=report.precise_sleeps,
    )


def donkey_segment(rate_hz: float, ticks: int, poller: bool = True) -> Segment:
    v = DonkeyVehicle()
    stamp = _graph(v, N_PARTS, "donkeycar" if poller else None)
    v.start(rate_hz=rate_hz, max_loop_count=ticks)
    t = np.asarray(stamp.times)
    return Segment.from_stamp(stamp, t - (t[0] + np.arange(len(t)) / rate_hz))


def floor_segment(rate_hz: float, ticks: int) -> Segment:
    """A bare loop sleeping to the deadlines ``t0 + k / rate_hz`` with ``time.sleep``, stamping each wake as the
    car's first part does: the machine's cost of waking up, with no runtime around it."""
    stamp = Stamp()
    late = np.empty(ticks)
    period = 1.0 / rate_hz
    t0 = time.monotonic()
    for k in range(ticks):
        deadline = t0 + k * period
        left = deadline - time.monotonic()
        if left > 0:
            time.sleep(left)
        stamp.run()
        late[k] = stamp.times[-1] - deadline
    return Segment.from_stamp(stamp, late)


def run_segment(
    cfg: Config, ticks: int, use_uvloop: bool, long_run: bool = False, pause_s: float = SETTLE_S
) -> Segment:
    _settle(pause_s)
    if cfg.who == "floor":
        seg = floor_segment(cfg.rate_hz, ticks)
    elif cfg.who == "donkeycar":
        seg = donkey_segment(cfg.rate_hz, ticks, cfg.poller)
    else:
        seg = ours_segment(cfg.rate_hz, ticks, use_uvloop, cfg.who == "ours_precise", cfg.poller)
    seg.long_run = long_run
    return seg


def configs(with_donkey: bool) -> dict[str, list[Config]]:
    """The configurations of each group, in their first round's order."""
    groups: dict[str, list[Config]] = {}
    for rate in RATES:
        who = ["ours", *(["ours_precise"] if rate in PRECISE_RATES else []), "donkeycar", "floor"]
        groups[str(rate)] = [Config(str(rate), w, rate, True) for w in who if with_donkey or w != "donkeycar"]
    who = ["ours", "donkeycar", "floor"]
    groups[IDLE] = [Config(IDLE, w, IDLE_HZ, False) for w in who if with_donkey or w != "donkeycar"]
    return groups


def _ticks(cfg: Config, rnd: int, opts: dict) -> tuple[int, bool]:
    """Ticks of ``cfg``'s segment in round ``rnd``, and whether it is the configuration's long run: the first
    round runs the cars (ours in both modes, Donkeycar's) for ``ticks`` (x5 at 1 kHz), the timing figures' run."""
    if rnd == 0 and cfg.group != IDLE and cfg.who != "floor":
        return opts["ticks"] * (5 if cfg.rate_hz > 100 else 1), True
    return max(round(opts["segment_s"] * cfg.rate_hz), MIN_SEGMENT_TICKS), False


def run_rounds(opts: dict, use_uvloop: bool, with_donkey: bool) -> dict[Config, list[Segment]]:
    groups = configs(with_donkey)
    segments: dict[Config, list[Segment]] = {c: [] for g in groups.values() for c in g}
    pause = min(SETTLE_S, opts["segment_s"] / 4)
    for cfg in segments:  # warm up every code path once, so the first round does not pay for it
        run_segment(cfg, MIN_SEGMENT_TICKS, use_uvloop, pause_s=pause)
    for rnd in range(opts["rounds"]):
        for group in groups.values():
            shift = rnd % len(group)
            for cfg in group[shift:] + group[:shift]:
                ticks, long_run = _ticks(cfg, rnd, opts)
                segments[cfg].append(run_segment(cfg, ticks, use_uvloop, long_run, pause))
    return segments


# ----------------------------------------------------------------------------------------------- figures
def _spread(values: list[float]) -> dict[str, float | list[float]]:
    return {"median": statistics.median(values), "min": min(values), "max": max(values), "rounds": values}


def rate_error(segments: list[Segment], rate_hz: float) -> tuple[float, float]:
    """Rate error and its standard error in ppm: one least-squares slope (seconds per tick) through every
    segment's tick start times, each segment with its own offset."""
    sxx = sxy = rss = 0.0
    n = 0
    for s in segments:
        k = np.arange(len(s.times), dtype=float)
        k -= k.mean()
        t = s.times - s.times.mean()
        sxx += float(k @ k)
        sxy += float(k @ t)
        n += len(k)
    slope = sxy / sxx
    for s in segments:
        k = np.arange(len(s.times), dtype=float)
        k -= k.mean()
        rss += float(np.sum((s.times - s.times.mean() - slope * k) ** 2))
    dof = n - len(segments) - 1
    se = (rss / dof / sxx) ** 0.5 if dof > 0 else float("nan")
    return (1.0 / slope / rate_hz - 1.0) * 1e6, se / slope * 1e6


def figures(cfg: Config, segs: list[Segment]) -> dict:
    long_runs = [s for s in segs if s.long_run]
    timed = long_runs or segs
    err, se = rate_error(timed, cfg.rate_hz)
    # Donkeycar's lateness grows with its drift, so with the run's length: only its long run counts
    late = np.concatenate([s.lateness_s for s in (timed if cfg.who == "donkeycar" else segs)]) * 1e3
    cpu, per_tick = _spread([s.cpu_pct for s in segs]), _spread([s.us_per_tick for s in segs])
    return {
        "rate_error_ppm": err,
        "rate_error_se_ppm": se,
        "rate_error_ticks": sum(len(s.times) for s in timed),
        # a deadline loop's rate error is the deadlines it skipped (a stall of the machine, or of the loop)
        "rate_error_skipped_deadlines": sum(s.skipped_deadlines for s in timed),
        "lateness_p50_ms": float(np.percentile(late, 50)),
        "lateness_p99_ms": float(np.percentile(late, 99)),
        "lateness_max_ms": float(late.max()),
        "lateness_ticks": len(late),
        **_p99_per_round(cfg, segs),
        "skipped_deadlines": sum(s.skipped_deadlines for s in segs),
        "cpu_pct": cpu["median"],
        "cpu_pct_min": cpu["min"],
        "cpu_pct_max": cpu["max"],
        "cpu_pct_rounds": cpu["rounds"],
        "cpu_us_per_tick": per_tick["median"],
        "cpu_us_per_tick_min": per_tick["min"],
        "cpu_us_per_tick_max": per_tick["max"],
        "cpu_us_per_tick_rounds": per_tick["rounds"],
        **_spin_window(segs),
    }


def _spin_window(segs: list[Segment]) -> dict:
    """Precise mode's learned spin window (ms), median over the segments: what each tick spun at most, and so
    most of what precise mode costs over the default; it follows the machine's wake-up lateness."""
    windows = [s.spin_window_ms for s in segs if s.spin_window_ms is not None]
    if not windows:
        return {}
    two = sum(s.precise_sleeps == 2 for s in segs)  # segments that ended sleeping twice before the spin
    return {"spin_window_ms": statistics.median(windows), "spin_window_ms_rounds": windows, "two_sleeps": two}


def _p99_per_round(cfg: Config, segs: list[Segment]) -> dict:
    """Each segment's own lateness p99 and their median: unlike the pooled p99, one segment caught in a stall
    of the machine does not move it (Donkeycar's lateness is its drift: no deadlines, no per-round figure)."""
    if cfg.who == "donkeycar":
        return {}
    p99 = [float(np.percentile(s.lateness_s, 99)) * 1e3 for s in segs]
    return {"lateness_p99_ms_median_of_rounds": statistics.median(p99), "lateness_p99_ms_rounds": p99}


def add_ratios(row: dict, who: str) -> None:
    """``row[who]``'s CPU over Donkeycar's, per round: median, min, max."""
    ours, dk = row[who]["cpu_pct_rounds"], row["donkeycar"]["cpu_pct_rounds"]
    r = _spread([a / b for a, b in zip(ours, dk, strict=True)])
    row[who].update(cpu_ratio=r["median"], cpu_ratio_min=r["min"], cpu_ratio_max=r["max"], cpu_ratio_rounds=r["rounds"])


def _flat_out_tick(make: str, n_parts: int, ticks: int, use_uvloop: bool) -> float:
    """Seconds per tick of a car with ``n_parts`` trivial parts, run with no wait between ticks: from the first
    tick's start to the last's, as the graph's first part stamps them, the same for both cars. So what a drive
    does once, before its first tick and after its last (ours: starting the drive, its end-of-drive report,
    whose per-part figures grow with the parts; Donkeycar's: nothing here, its ``update_parts()`` is called
    bare), is not counted as a tick's cost: spread over the ticks it read as about 0.06 µs a part."""
    if make == "ours":
        v = Vehicle()
        stamp = _graph(v, n_parts)
        run_blocking(v.run(1e9, ticks), use_uvloop=use_uvloop)  # a rate far above what the loop can do
    else:
        v = DonkeyVehicle()
        stamp = _graph(v, n_parts)
        for _ in range(ticks):
            v.update_parts()  # the body of Donkeycar's loop, profiler included, without its sleep
    t = stamp.times
    if len(t) < 2:
        raise RuntimeError(f"loop benchmark: a flat-out run of {make} ran {len(t)} tick(s), at least 2 are needed")
    return (t[-1] - t[0]) / (len(t) - 1)


def overhead(ticks: int, repeats: int, use_uvloop: bool, with_donkey: bool) -> dict:
    """µs per part: (flat-out tick with 2 x N_PARTS parts - with none) / (2 x N_PARTS), each tick time the
    minimum over ``repeats`` interleaved runs."""
    n = N_PARTS * 2
    makers = ["ours", *(["donkeycar"] if with_donkey else [])]
    runs: dict[tuple[str, int], list[float]] = {(m, k): [] for m in makers for k in (0, n)}
    for _ in range(repeats):
        for m, k in runs:
            runs[(m, k)].append(_flat_out_tick(m, k, ticks, use_uvloop))
    out: dict = {}
    for m in makers:
        out[m] = (min(runs[(m, n)]) - min(runs[(m, 0)])) / n * 1e6
        out[f"{m}_rounds"] = [(f - b) / n * 1e6 for f, b in zip(runs[(m, n)], runs[(m, 0)], strict=True)]
    if with_donkey:
        out["ratio"] = out["ours"] / out["donkeycar"]
    return out


def measure(opts: dict, use_uvloop: bool, with_donkey: bool) -> dict:
    t0 = time.monotonic()
    machine = describe(with_load=True)  # the load before the runs: they add their own
    segments = run_rounds(opts, use_uvloop, with_donkey)
    results: dict = {
        "method": {**opts, "interleaved": "sequential", "idle_hz": IDLE_HZ, "uvloop": use_uvloop},
        "ticks": opts["ticks"],
        "uvloop": use_uvloop,
        "machine": machine,
        "rates": {},
        IDLE: {},
    }
    for cfg, segs in segments.items():
        results["rates" if cfg.group != IDLE else IDLE].setdefault(cfg.group, {})[cfg.who] = figures(cfg, segs)
    results[IDLE] = results[IDLE][IDLE]
    for row in [*results["rates"].values(), results[IDLE]]:
        if with_donkey:
            for who in ("ours", "ours_precise"):
                if who in row:
                    add_ratios(row, who)
    results["idle_cpu_pct"] = {who: r["cpu_pct"] for who, r in results[IDLE].items()}
    results["overhead_us"] = overhead(opts["overhead_ticks"], opts["overhead_repeats"], use_uvloop, with_donkey)
    results["seconds"] = time.monotonic() - t0
    return results


# ------------------------------------------------------------------------------------------------- table
def _range(r: dict, key: str, digits: int = 2) -> str:
    return f"{r[key + '_min']:.{digits}f}-{r[key + '_max']:.{digits}f}"


def table(results: dict) -> str:
    has_dk = "donkeycar" in results["overhead_us"]
    rounds = results["method"]["rounds"]
    pt = PrettyTable()
    pt.field_names = [
        "rate",
        "loop",
        "rate error (ppm)",
        "skipped",
        "lateness p50 (ms)",
        "p99 (ms)",
        "max (ms)",
        "p99 per round, median",
        "CPU % median",
        "CPU % min-max",
        "µs/tick",
        "µs/tick min-max",
        "CPU / Donkeycar (min-max)",
    ]
    rows = [(f"{rate} Hz", row) for rate, row in results["rates"].items()]
    rows.append((f"{IDLE_HZ} Hz idle", results[IDLE]))
    for rate, row in rows:
        for who, label in LABELS.items():
            if who not in row:
                continue
            r = row[who]
            ratio = f"{r['cpu_ratio']:.2f} ({_range(r, 'cpu_ratio')})" if "cpu_ratio" in r else ""
            pt.add_row(
                [
                    rate,
                    label,
                    f"{r['rate_error_ppm']:+,.1f} ± {r['rate_error_se_ppm']:,.1f}",
                    r["skipped_deadlines"] if who != "donkeycar" else "",
                    f"{r['lateness_p50_ms']:.3f}",
                    f"{r['lateness_p99_ms']:.3f}",
                    f"{r['lateness_max_ms']:.3f}",
                    f"{r['lateness_p99_ms_median_of_rounds']:.3f}" if who != "donkeycar" else "",
                    f"{r['cpu_pct']:.2f}",
                    _range(r, "cpu_pct"),
                    f"{r['cpu_us_per_tick']:.0f}",
                    _range(r, "cpu_us_per_tick", 0),
                    ratio,
                ]
            )
    out = [pt.get_string()]
    ov = results["overhead_us"]
    line = f"per-part overhead (profiling on, flat out, min of {results['method']['overhead_repeats']}): "
    line += f"asyncdonkey {ov['ours']:.2f} µs"
    if has_dk:
        line += f", Donkeycar {ov['donkeycar']:.2f} µs (ours/Donkeycar {ov['ratio']:.2f})"
    out.append(line)
    idle = results[IDLE]
    line = f"idle CPU ({N_PARTS} no-op parts, no poller, {IDLE_HZ} Hz): asyncdonkey {idle['ours']['cpu_pct']:.2f} %"
    if has_dk:
        line += f", Donkeycar {idle['donkeycar']['cpu_pct']:.2f} % (ours/Donkeycar {idle['ours']['cpu_ratio']:.2f})"
    line += f"; floor {idle['floor']['cpu_pct']:.2f} %"
    out.append(line)
    if has_dk:
        for rate, row in results["rates"].items():
            ours, dk = row["ours"], row["donkeycar"]
            ratio = abs(dk["rate_error_ppm"]) / max(abs(ours["rate_error_ppm"]), 1.0)
            out.append(
                f"{rate} Hz: Donkeycar's rate error is {ratio:,.0f}x ours"
                f" ({dk['rate_error_ppm']:+,.0f} vs {ours['rate_error_ppm']:+,.1f} ppm);"
                f" CPU ours/Donkeycar {ours['cpu_ratio']:.2f}"
                + (
                    f", precise {row['ours_precise']['cpu_ratio']:.2f}"
                    f" (spin window {row['ours_precise']['spin_window_ms']:.3f} ms,"
                    f" two sleeps in {row['ours_precise']['two_sleeps']} of"
                    f" {len(row['ours_precise']['spin_window_ms_rounds'])} rounds)"
                    if "ours_precise" in row
                    else ""
                )
                + f"; per tick {ours['cpu_us_per_tick']:.0f} µs vs {dk['cpu_us_per_tick']:.0f},"
                f" floor {row['floor']['cpu_us_per_tick']:.0f}"
            )
    out.append(
        f"CPU: median over {rounds} interleaved rounds of {results['method']['segment_s']} s segments;"
        " ratios per round."
        f" Rate error (± its standard error) and Donkeycar's lateness from {results['ticks']}-tick runs (x5 at 1 kHz)."
    )
    out.append(
        f"machine: {results['machine']}; {N_PARTS} parts + a {POLL_HZ} Hz poller; {results['seconds']:.0f} s in all"
    )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer, shorter segments (about a minute)")
    parser.add_argument("--ticks", type=int, help=f"ticks of the long timing runs (default {FULL['ticks']})")
    parser.add_argument("--rounds", type=int, help=f"interleaved rounds (default {FULL['rounds']})")
    parser.add_argument("--segment-s", type=float, help=f"seconds per segment (default {FULL['segment_s']})")
    parser.add_argument("--overhead-ticks", type=int, help="ticks per flat-out run of the per-part overhead")
    parser.add_argument("--overhead-repeats", type=int, help="flat-out runs per car of the per-part overhead")
    parser.add_argument("--no-uvloop", action="store_true")
    parser.add_argument("--no-donkeycar", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = parser.parse_args(argv)
    logging.disable(logging.INFO)  # the per-run profiler reports are not the figures
    opts = dict(QUICK if args.quick else FULL)
    for key in ("ticks", "rounds", "segment_s", "overhead_ticks", "overhead_repeats"):
        if getattr(args, key) is not None:
            opts[key] = getattr(args, key)
    if min(opts["rounds"], opts["overhead_ticks"], opts["overhead_repeats"]) < 1:
        parser.error("--rounds, --overhead-ticks and --overhead-repeats must be >= 1")
    if opts["ticks"] < 2 or opts["segment_s"] <= 0:
        parser.error("--ticks must be >= 2 and --segment-s > 0")
    results = measure(opts, not args.no_uvloop, DonkeyVehicle is not None and not args.no_donkeycar)
    print(json.dumps(results, indent=2) if args.json else table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
