"""``asyncdonkey report``: a drive's timing as one self-contained HTML page (inline SVG, no plotting library).

::

    asyncdonkey report data/drive.mcap                 # writes data/drive.html
    asyncdonkey report data/tub_1 -o tub_1.html        # a tub: record intervals only

From an MCAP recording (:class:`~asyncdonkey.parts.mcap.McapRecorder` with its timing topics) the page shows
every tick, part run and latency sample the recording holds (the recorder writes each sample of the drive once;
samples it could not, having fallen more than the profiler's window behind, are counted and the page says how
many):

* **lateness over time**: each tick's start minus its deadline, with the ticks whose previous tick overran
  its period marked (red) and the deadlines the loop skipped because it was more than a period behind (orange
  lines);
* **the lateness histogram** and its percentiles;
* **tick duration over time** against the period;
* **per-part time distributions**: for each part a box (p25-p75), its median, whiskers to p1 and p99 and a dot
  at the maximum, with the figures in a table;
* **sensing-to-actuation latency** per actuator over time, when the car has actuators.

A tub has no loop timing; its page shows the intervals between recorded records (``_timestamp_ms``), which
reveal stalls and dropped ticks, and says so. Everything is computed here and drawn as SVG in the page, so the
file opens anywhere, offline, and can be attached to an issue.
"""

from __future__ import annotations

import argparse
import html
import math
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import AsyncdonkeyError

__all__ = ["DriveTiming", "ReportError", "add_report_parser", "load_timing", "render_html", "write_report"]

EXIT_USAGE = 2


class ReportError(AsyncdonkeyError, ValueError):
    """A recording without the timing a report needs; the message names the file."""


_COLORS = ["#2563eb", "#16a34a", "#d97706", "#9333ea", "#dc2626", "#0891b2", "#4b5563", "#db2777"]


@dataclass
class DriveTiming:
    """The timing series of one recording, times in seconds from its start, durations in ms."""

    source: str
    kind: str  # "mcap" or "tub"
    t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """tick times (s): each tick's start (MCAP), in tick order"""
    lateness_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    duration_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """each tick's duration (NaN where unknown); a tub: the interval before each record"""
    overrun_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """each tick's overrun (NaN where unknown)"""
    skipped_at: list[tuple[float, int]] = field(default_factory=list)
    """(time, deadlines skipped then)"""
    parts: dict[str, np.ndarray] = field(default_factory=dict)
    latency: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    """actuator → (times, ms)"""
    overruns: int = 0
    skipped_deadlines: int = 0
    period_ms: float | None = None
    timing_dropped: int = 0
    """timing samples the recorder could not write (they left the profiler's window first)"""


def load_timing(path: str | os.PathLike[str]) -> DriveTiming:
    """Read the timing of an MCAP recording, or the record intervals of a tub."""
    from .recordings import check_recording, is_mcap

    check_recording(path)
    if is_mcap(path):
        return _load_mcap(path)
    return _load_tub(path)


def _load_mcap(path: str | os.PathLike[str]) -> DriveTiming:
    from ..parts.mcap.encode import LATENCY_TOPIC, PARTS_TOPIC, TICK_TOPIC
    from ..parts.mcap.reader import read_mcap

    d = DriveTiming(os.fspath(path), "mcap")
    # tick number → [log ns, lateness, duration, overrun, overruns, skipped, when the counters were read (ns)]
    ticks: dict[int, list[Any]] = {}
    parts: dict[str, list[float]] = {}
    lat: dict[str, list[tuple[int, float]]] = {}
    for m in read_mcap(path, {TICK_TOPIC, PARTS_TOPIC, LATENCY_TOPIC}):
        v = m.value
        if not isinstance(v, dict):  # a message of another shape than the recorder writes: not timing
            continue
        if m.topic == TICK_TOPIC:
            _add_tick(ticks, m.log_time_ns, v)
            dropped = v.get("timing_dropped")
            if isinstance(dropped, int):
                d.timing_dropped = max(d.timing_dropped, dropped)
        elif m.topic == PARTS_TOPIC:
            for name, ms in _figures(v):
                parts.setdefault(name, []).append(ms)
        else:
            for name, ms in _figures(v):
                lat.setdefault(name, []).append((m.log_time_ns, ms))
    started = sorted(k for k, row in ticks.items() if row[0] is not None and row[1] is not None)
    if not started:
        raise ReportError(f"{os.fspath(path)}: no {TICK_TOPIC} messages (recorded with timing=False?)")
    t0 = min([ticks[started[0]][0], *(ns for v in lat.values() for ns, _ in v)])
    rows = [ticks[k] for k in started]
    d.t = np.array([(r[0] - t0) / 1e9 for r in rows])
    d.lateness_ms, d.duration_ms, d.overrun_ms = (np.array([_num(r[i]) for r in rows]) for i in (1, 2, 3))
    _counters(d, rows, t0)
    d.parts = {k: np.array(v) for k, v in parts.items()}
    d.latency = {k: (np.array([(a - t0) / 1e9 for a, _ in v]), np.array([b for _, b in v])) for k, v in lat.items()}
    if len(d.t) > 2:
        d.period_ms = float(np.median(np.diff(d.t))) * 1e3
    return d


def _figures(v: dict[str, Any]) -> Iterator[tuple[str, float]]:
    """The ``name: milliseconds`` pairs of a parts or latency message that are numbers (what the recorder wrote)."""
    for name, ms in v.items():
        if isinstance(ms, int | float) and not isinstance(ms, bool):
            yield str(name), float(ms)


def _add_tick(ticks: dict[int, list[Any]], log_ns: int, v: dict[str, Any]) -> None:
    """File a tick message's figures under the tick they belong to. A message carries its own tick's duration,
    overrun and the drive's counters after it; files written before ``timing_dropped`` existed carried the
    previous tick's (and were stamped with the recorder's run rather than the tick's start)."""
    k = v.get("tick")
    if not isinstance(k, int):
        return
    row = ticks.setdefault(k, [None] * 7)
    row[0], row[1] = log_ns, v.get("lateness_ms")
    own = "timing_dropped" in v
    ended = row if own else ticks.setdefault(k - 1, [None] * 7)  # the tick the figures and counters are of
    ended[2], ended[3] = v.get("duration_ms"), v.get("overrun_ms")
    ended[4], ended[5] = v.get("overruns"), v.get("skipped_deadlines")
    ended[6] = None if own else log_ns  # an older file's counters were read by the next tick's recorder run


def _counters(d: DriveTiming, rows: list[list[Any]], t0: int) -> None:
    """The drive's overrun and skipped-deadline counts, and where deadlines were skipped: at the end of the tick
    whose counters show more than the last known ones (a tick's counters are read after it ended)."""
    last_skipped = 0
    for i, r in enumerate(rows):
        if isinstance(r[4], int):
            d.overruns = r[4]
        skipped = r[5]
        if not isinstance(skipped, int):
            continue
        if skipped > last_skipped:
            if r[6] is not None:  # an older file: when the next tick's recorder read them
                end = (r[6] - t0) / 1e9
            else:
                end = d.t[i] + (d.duration_ms[i] / 1e3 if math.isfinite(d.duration_ms[i]) else 0.0)
            d.skipped_at.append((float(end), skipped - last_skipped))
        last_skipped = max(last_skipped, skipped)
    d.skipped_deadlines = last_skipped


def _load_tub(path: str | os.PathLike[str]) -> DriveTiming:
    from ..parts.tub import Tub

    tub = Tub(path)
    stamps = np.array(
        [r.raw["_timestamp_ms"] for r in tub.records() if isinstance(r.raw.get("_timestamp_ms"), int | float)],
        dtype=float,
    )
    d = DriveTiming(str(tub.base_path), "tub")
    if stamps.size < 2:
        raise ReportError(f"{tub.base_path}: fewer than two timestamped records")
    d.t = (stamps[1:] - stamps[0]) / 1e3
    d.duration_ms = np.diff(stamps)
    d.period_ms = float(np.median(d.duration_ms))
    d.lateness_ms = np.zeros(0)
    d.overrun_ms = np.zeros(0)
    return d


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) else math.nan


# ----------------------------------------------------------------------------------------------- SVG
_W, _H, _ML, _MR, _MT, _MB = 860, 240, 60, 16, 14, 34


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo]
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw), default=raw)
    start = math.ceil(lo / step) * step
    return [start + i * step for i in range(int((hi - start) / step) + 1)]


def _fmt(v: float) -> str:
    return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"


class _Axes:
    def __init__(self, x0: float, x1: float, y0: float, y1: float, w: int = _W, h: int = _H, ml: int = _ML) -> None:
        self.ml = ml
        self.x0, self.x1 = x0, (x1 if x1 > x0 else x0 + 1)
        self.y0, self.y1 = y0, (y1 if y1 > y0 else y0 + 1)
        self.w, self.h = w, h
        self.parts: list[str] = []

    def x(self, v: float) -> float:
        return self.ml + (v - self.x0) / (self.x1 - self.x0) * (self.w - self.ml - _MR)

    def y(self, v: float) -> float:
        return self.h - _MB - (v - self.y0) / (self.y1 - self.y0) * (self.h - _MT - _MB)

    def frame(self, xlabel: str, ylabel: str) -> None:
        p = self.parts
        for v in _ticks(self.y0, self.y1):
            y = self.y(v)
            p.append(f'<line x1="{_ML}" x2="{self.w - _MR}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e5e7eb"/>')
            p.append(f'<text x="{_ML - 6}" y="{y + 4:.1f}" text-anchor="end">{_fmt(v)}</text>')
        for v in _ticks(self.x0, self.x1, 8):
            x = self.x(v)
            p.append(f'<text x="{x:.1f}" y="{self.h - _MB + 16}" text-anchor="middle">{_fmt(v)}</text>')
        p.append(
            f'<rect x="{_ML}" y="{_MT}" width="{self.w - _ML - _MR}" height="{self.h - _MT - _MB}" '
            'fill="none" stroke="#9ca3af"/>'
        )
        p.append(f'<text x="{(self.w + _ML) / 2}" y="{self.h - 4}" text-anchor="middle">{html.escape(xlabel)}</text>')
        p.append(
            f'<text x="14" y="{(self.h - _MB) / 2}" text-anchor="middle" '
            f'transform="rotate(-90 14 {(self.h - _MB) / 2})">{html.escape(ylabel)}</text>'
        )

    def polyline(self, xs: np.ndarray, ys: np.ndarray, color: str, width: float = 1.0) -> None:
        ok = np.isfinite(xs) & np.isfinite(ys)
        xs, ys = xs[ok], ys[ok]
        if xs.size > 4000:  # keep the page small: min/max per pixel column preserves every spike
            xs, ys = _decimate(xs, ys, self.w * 2)
        pts = " ".join(f"{self.x(a):.1f},{self.y(b):.1f}" for a, b in zip(xs, ys, strict=True))
        self.parts.append(f'<polyline points="{pts}" fill="none" stroke="{color}" stroke-width="{width}"/>')

    def svg(self, extra: str = "") -> str:
        body = "".join(self.parts)
        return (
            f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.w}" height="{self.h}" '
            f'font-family="sans-serif" font-size="11">{body}{extra}</svg>'
        )


def _decimate(xs: np.ndarray, ys: np.ndarray, columns: int) -> tuple[np.ndarray, np.ndarray]:
    edges = np.linspace(xs[0], xs[-1], columns + 1)
    idx = np.clip(np.searchsorted(edges, xs, side="right") - 1, 0, columns - 1)
    keep: list[int] = []
    for c in np.unique(idx):
        sel = np.nonzero(idx == c)[0]
        keep.extend(sorted({int(sel[np.argmin(ys[sel])]), int(sel[np.argmax(ys[sel])])}))
    k = np.array(keep)
    return xs[k], ys[k]


def _top(values: Sequence[np.ndarray]) -> float:
    finite = [v[np.isfinite(v)] for v in values]
    tops = [float(v.max()) for v in finite if v.size]
    return max(tops) * 1.05 if tops else 1.0


def lateness_chart(d: DriveTiming) -> str:
    ax = _Axes(0, float(d.t[-1]) if d.t.size else 1, 0, _top([d.lateness_ms]))
    ax.frame("time (s)", "lateness (ms)")
    for t, n in d.skipped_at:
        x = ax.x(t)
        ax.parts.append(
            f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{_MT}" y2="{_H - _MB}" stroke="#f59e0b" stroke-width="1.5">'
            f"<title>{n} deadline(s) skipped at {t:.2f} s</title></line>"
        )
    ax.polyline(d.t, d.lateness_ms, _COLORS[0])
    over = np.nonzero(d.overrun_ms[:-1] > 0)[0]  # marked on the tick after the overrun, the one it made late
    for i in over[:2000]:
        ax.parts.append(
            f'<circle cx="{ax.x(d.t[i + 1]):.1f}" cy="{ax.y(d.lateness_ms[i + 1]):.1f}" r="2.5" fill="#dc2626">'
            f"<title>previous tick overran by {d.overrun_ms[i]:.2f} ms</title></circle>"
        )
    return ax.svg()


def duration_chart(d: DriveTiming, label: str) -> str:
    top = _top([d.duration_ms]) if d.period_ms is None else max(_top([d.duration_ms]), d.period_ms * 1.1)
    ax = _Axes(0, float(d.t[-1]) if d.t.size else 1, 0, top)
    ax.frame("time (s)", label)
    if d.period_ms is not None and d.kind == "mcap":
        y = ax.y(d.period_ms)
        ax.parts.append(
            f'<line x1="{_ML}" x2="{_W - _MR}" y1="{y:.1f}" y2="{y:.1f}" stroke="#dc2626" stroke-dasharray="4 3">'
            f"<title>period {d.period_ms:.2f} ms</title></line>"
        )
    ax.polyline(d.t, d.duration_ms, _COLORS[1])
    return ax.svg()


def histogram(values: np.ndarray, label: str, bins: int = 50) -> str:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return "<p>no samples</p>"
    hi = float(np.percentile(v, 99.9)) if v.size > 100 else float(v.max())
    hi = hi if hi > v.min() else float(v.min()) + 1e-3
    counts, edges = np.histogram(np.clip(v, v.min(), hi), bins=bins, range=(float(v.min()), hi))
    ax = _Axes(float(edges[0]), float(edges[-1]), 0, float(counts.max()) * 1.05)
    ax.frame(label + (" (last bin: at or above)" if hi < v.max() else ""), "ticks")
    for c, a, b in zip(counts, edges[:-1], edges[1:], strict=True):
        if c:
            x0, x1, y = ax.x(a), ax.x(b), ax.y(c)
            ax.parts.append(
                f'<rect x="{x0:.1f}" y="{y:.1f}" width="{max(x1 - x0 - 1, 1):.1f}" height="{ax.y(0) - y:.1f}" '
                f'fill="{_COLORS[0]}"><title>{a:.3f}-{b:.3f} ms: {c}</title></rect>'
            )
    return ax.svg()


def box_plot(series: dict[str, np.ndarray]) -> str:
    names = [n for n, v in series.items() if np.isfinite(v).any()]
    if not names:
        return "<p>no part times recorded</p>"
    row = 26
    h = _MT + _MB + row * len(names)
    top = max(float(np.nanmax(series[n])) for n in names) * 1.05
    ax = _Axes(0, top, 0, 1, h=h, ml=150)
    for i, n in enumerate(names):
        v = series[n][np.isfinite(series[n])]
        p1, p25, p50, p75, p99 = np.percentile(v, [1, 25, 50, 75, 99])
        y = _MT + row * i + row / 2
        c = _COLORS[i % len(_COLORS)]
        title = f"{n}: p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {v.max():.3f} ms ({v.size} runs)"
        ax.parts.append(
            f"<g><title>{html.escape(title)}</title>"
            f'<line x1="{ax.x(p1):.1f}" x2="{ax.x(p99):.1f}" y1="{y}" y2="{y}" stroke="{c}"/>'
            f'<rect x="{ax.x(p25):.1f}" y="{y - 7}" width="{max(ax.x(p75) - ax.x(p25), 1):.1f}" height="14" '
            f'fill="{c}" fill-opacity="0.35" stroke="{c}"/>'
            f'<line x1="{ax.x(p50):.1f}" x2="{ax.x(p50):.1f}" y1="{y - 7}" y2="{y + 7}" stroke="{c}" '
            'stroke-width="2"/>'
            f'<circle cx="{ax.x(float(v.max())):.1f}" cy="{y}" r="3" fill="{c}"/></g>'
            f'<text x="144" y="{y + 4}" text-anchor="end" fill="#374151">{html.escape(n)}</text>'
        )
    for v in _ticks(0, top, 8):
        ax.parts.append(f'<text x="{ax.x(v):.1f}" y="{h - _MB + 16}" text-anchor="middle">{_fmt(v)}</text>')
    ax.parts.append(f'<line x1="150" x2="150" y1="{_MT}" y2="{h - _MB}" stroke="#9ca3af"/>')
    ax.parts.append(f'<text x="{(_W + 150) / 2}" y="{h - 4}" text-anchor="middle">time per run (ms)</text>')
    return ax.svg()


def latency_chart(d: DriveTiming) -> str:
    ts = [t for t, _ in d.latency.values()]
    ax = _Axes(0, max(float(t[-1]) for t in ts if t.size), 0, _top([ms for _, ms in d.latency.values()]))
    ax.frame("time (s)", "latency (ms)")
    legend = []
    for i, (name, (t, ms)) in enumerate(d.latency.items()):
        c = _COLORS[(i + 2) % len(_COLORS)]
        ax.polyline(t, ms, c)
        legend.append(f'<text x="{_ML + 8}" y="{_MT + 14 + 14 * i}" fill="{c}">{html.escape(name)}</text>')
    return ax.svg("".join(legend))


# ----------------------------------------------------------------------------------------------- page
def _stats_row(name: str, v: np.ndarray) -> str:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return ""
    p50, p90, p99 = np.percentile(v, [50, 90, 99])
    cells = [f"{x:.3f}" for x in (v.mean(), p50, p90, p99, v.max())]
    return f"<tr><td>{html.escape(name)}</td><td>{v.size}</td>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"


def _table(rows: list[tuple[str, np.ndarray]]) -> str:
    head = "<tr><th></th><th>n</th><th>avg</th><th>p50</th><th>p90</th><th>p99</th><th>max</th></tr>"
    return f"<table>{head}{''.join(_stats_row(n, v) for n, v in rows)}</table>"


def render_html(d: DriveTiming) -> str:
    """The report page for ``d``."""
    title = f"Drive timing: {Path(d.source).name}"
    out = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>",
        "body{font-family:sans-serif;max-width:900px;margin:2em auto;color:#111827}"
        "table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #d1d5db;padding:2px 8px;"
        "text-align:right}td:first-child{text-align:left}.note{color:#4b5563}",
        "</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='note'>{html.escape(d.source)}</p>",
    ]
    if d.kind == "mcap":
        duration = float(d.t[-1]) if d.t.size else 0.0
        rate = f"{1e3 / d.period_ms:.1f} Hz" if d.period_ms else "?"
        out.append(
            f"<p>{d.t.size} ticks over {duration:.1f} s (about {rate}); "
            f"<b>{d.overruns}</b> overruns (red dots: the tick after one); "
            f"<b>{d.skipped_deadlines}</b> skipped deadlines (orange lines).</p>"
        )
        if d.timing_dropped:
            out.append(
                f"<p><b>{d.timing_dropped}</b> timing samples are not in this recording: the recorder fell more "
                "than the profiler's window behind and they left it before they were written.</p>"
            )
        out += ["<h2>Lateness over time</h2>", lateness_chart(d)]
        out += ["<h2>Lateness histogram</h2>", histogram(d.lateness_ms, "lateness (ms)")]
        out += ["<h2>Tick duration</h2>", duration_chart(d, "tick duration (ms)")]
        out.append(_table([("lateness (ms)", d.lateness_ms), ("tick duration (ms)", d.duration_ms)]))
        out += ["<h2>Time per part</h2>", box_plot(d.parts), _table(list(d.parts.items()))]
        if d.latency:
            out += ["<h2>Sensing-to-actuation latency</h2>", latency_chart(d)]
            out.append(_table([(n, ms) for n, (_, ms) in d.latency.items()]))
        else:
            out.append("<p class='note'>No actuator latency recorded (no actuators in this car).</p>")
    else:
        out.append(
            "<p class='note'>A tub records no loop timing: shown are the intervals between recorded records, "
            "where stalls and dropped ticks show as long gaps. Record with McapRecorder for lateness, part "
            "times and latency.</p>"
        )
        out += ["<h2>Record intervals</h2>", duration_chart(d, "interval (ms)")]
        out += ["<h2>Interval histogram</h2>", histogram(d.duration_ms, "interval (ms)")]
        out.append(_table([("interval (ms)", d.duration_ms)]))
    out.append("</body></html>")
    return "\n".join(out)


def write_report(source: str | os.PathLike[str], output: str | os.PathLike[str] | None = None) -> Path:
    """Write the HTML report of ``source``; returns its path (default: beside the source, ``.html``)."""
    d = load_timing(source)
    src = Path(source)
    out = Path(output) if output is not None else src.with_suffix(".html") if src.is_file() else src / "timing.html"
    out.write_text(render_html(d), encoding="utf-8")
    return out


def add_report_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "report",
        help="write a drive's timing as one HTML page (lateness, histogram, part times, latency)",
        description="Timing report of an MCAP recording (or the record intervals of a tub) as one "
        "self-contained HTML page.",
    )
    p.add_argument(
        "source",
        metavar="RECORDING",
        help="an .mcap file recorded with McapRecorder (mcap extra; the full timing), or a tub directory "
        "(record intervals only)",
    )
    p.add_argument(
        "-o",
        "--output",
        default=None,
        metavar="FILE",
        help="the HTML file to write (default: beside the source: drive.mcap -> drive.html, a tub -> TUB/timing.html)",
    )
    p.set_defaults(handler=report_main)
    return p


def report_main(args: argparse.Namespace) -> int:
    from ..parts.tub import TubError

    try:
        out = write_report(args.source, args.output)
    except (TubError, OSError, ValueError, ImportError) as exc:
        print(f"asyncdonkey report: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(out)
    return 0
