"""Per-part and per-tick timing with bounded memory, reported in Donkeycar's format.

Donkeycar's profiler appends every sample to a list for the whole drive, so hours of driving grow it without
bound. Here each series keeps the most recent ``window`` samples in a fixed ``array('d')`` ring (percentiles
and averages come from that window) plus run-long count, min and max. As in Donkeycar, the first sample of each
part is ignored (one-off start-up cost) and so is the last (it may have been cut short by a stop).

Recording sits on the hot path for every part of every tick, so the parts of the tick do not record durations
one series at a time: the tick writes one row of a :class:`TickTable` (its start, then each part's end time, one
float store per part), and each part's durations are worked out from those rows only when a report asks
(:class:`TableSeries`, which reads like a :class:`Series`); so are the loop's lateness, tick duration and
overrun. Pipelined parts and latencies record into :class:`Series` rings.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterable
from typing import Any

import numpy as np
from prettytable import PrettyTable

__all__ = ["DEFAULT_WINDOW", "PERCENTILES", "Profiler", "Series", "TableSeries", "TickTable"]

#: samples kept per series for percentiles (at 20 Hz: about 13.6 minutes of driving)
DEFAULT_WINDOW = 16384
PERCENTILES = (50.0, 90.0, 99.0, 99.9)


class Series:
    """A bounded series of durations in seconds."""

    __slots__ = ("_buf", "count", "evicted_max", "evicted_min", "first", "name", "skip_first", "window")

    def __init__(self, name: str, window: int = DEFAULT_WINDOW, skip_first: bool = True) -> None:
        self.name = name
        self.window = window
        self.skip_first = skip_first
        self._buf = array("d", bytes(8 * window))
        self.count = 0  # samples recorded into the ring (the skipped first one excluded)
        self.first: float | None = None
        # extremes of the samples that fell out of the window: with the window's own, the run-long extremes
        # (kept this way, not updated per sample, so that the newest sample, which the report ignores, never
        # leaks into them)
        self.evicted_min = math.inf
        self.evicted_max = -math.inf

    def record(self, value: float) -> None:
        if self.skip_first and self.first is None:
            self.first = value
            return
        i = self.count % self.window
        if self.count >= self.window:
            old = self._buf[i]
            if old > self.evicted_max:
                self.evicted_max = old
            if old < self.evicted_min:
                self.evicted_min = old
        self._buf[i] = value
        self.count += 1

    @property
    def last(self) -> float | None:
        """The newest sample, or ``None`` before the first."""
        return self._buf[(self.count - 1) % self.window] if self.count else None

    def at(self, n: int) -> float | None:
        """Sample number ``n`` (0-based, in recording order; the skipped first one not counted), or ``None`` if it
        is not recorded yet or has left the window. Safe from another thread while the loop records: a sample
        is stored before ``count`` counts it, and its slot is reused only ``window`` samples later."""
        count = self.count
        if n < 0 or n >= count or n < count - self.window:
            return None
        return self._buf[n % self.window]

    def first_readable(self) -> int:
        """The oldest sample number another thread can still read whole: the one at ``count - window`` shares its
        slot with the next sample, which the loop may be storing right now (it stores before it counts). A
        reader calls :meth:`at`, then this: a sample older than it may have been overwritten while read."""
        return max(0, self.count - self.window + 1)

    @property
    def max(self) -> float:
        """Run-long maximum of every sample recorded (the skipped first one excluded)."""
        return max(self.evicted_max, float(self.recent(drop_last=False).max(initial=-math.inf)))

    @property
    def min(self) -> float:
        return min(self.evicted_min, float(self.recent(drop_last=False).min(initial=math.inf)))

    def recent(self, drop_last: bool = True) -> np.ndarray:
        """The samples in the window, oldest first (the newest dropped when ``drop_last``)."""
        n = min(self.count, self.window)
        buf = np.frombuffer(self._buf, dtype=np.float64)
        if self.count <= self.window:
            out = buf[:n].copy()
        else:
            i = self.count % self.window
            out = np.concatenate((buf[i:], buf[:i]))
        return out[:-1] if drop_last and len(out) else out

    def summary(self, drop_last: bool = True) -> dict[str, float] | None:
        """max/min/avg and percentiles in milliseconds, or ``None`` with no samples."""
        arr = self.recent(drop_last)
        if len(arr) == 0:
            return None
        return _summary(arr, self.count, self.evicted_min, self.evicted_max)


def _summary(arr: np.ndarray, count: int, evicted_min: float, evicted_max: float) -> dict[str, float]:
    pct = np.percentile(arr, PERCENTILES)
    out = {
        "max": max(float(arr.max()), evicted_max) * 1e3,
        "min": min(float(arr.min()), evicted_min) * 1e3,
        "avg": float(arr.mean()) * 1e3,
        "count": float(count),
    }
    for p, v in zip(PERCENTILES, pct, strict=True):
        out[_pct_key(p)] = float(v) * 1e3
    return out


def _pct_key(p: float) -> str:
    return f"{p:g}%"


class TickTable:
    """The tick's timings: one row per tick in a ring of ``window`` rows, written in place by the tick.

    A row is ``[deadline, start, end of part 1, ..., end of part n, end]`` (``nan`` for a part its run condition
    skipped). Each part starts when the one before it (or the tick) ended, so its duration is its end minus the
    nearest earlier time in the row; the loop's own figures follow from the row too: lateness is start minus
    deadline, the tick's duration end minus start, its overrun that duration beyond the period. The tick writes
    the row from :meth:`offset` (``begun`` counts it from its start) and counts it with :meth:`commit`; a tick
    cut short is never counted.

    :meth:`values` works the figures out only when a report asks; :class:`TableSeries` reads one of them like a
    :class:`Series`. Run-long extremes: before rows are overwritten, in blocks of :data:`FOLD_ROWS` ticks, their
    figures are folded into run-long minima and maxima (a few microseconds every thousand ticks).
    """

    FOLD_ROWS = 1024
    #: figure columns after the parts' durations in :meth:`values`
    LATENESS, TICK, OVERRUN = -3, -2, -1

    __slots__ = (
        "_cache",
        "_fold",
        "begun",
        "buf",
        "evicted_count",
        "evicted_max",
        "evicted_min",
        "n_parts",
        "ncol",
        "period",
        "rows",
        "window",
    )

    def __init__(self, n_parts: int, period: float, window: int = DEFAULT_WINDOW) -> None:
        self.n_parts = n_parts
        self.ncol = n_parts + 3
        self.period = period
        self.window = window
        self.buf = array("d", bytes(8 * window * self.ncol))
        self.rows = 0  # ticks committed
        self.begun = 0  # ticks started (rows, or rows + 1 while a tick runs)
        self._fold = min(self.FOLD_ROWS, window)
        nfig = n_parts + 3
        self.evicted_min = np.full(nfig, math.inf)
        self.evicted_max = np.full(nfig, -math.inf)
        self.evicted_count = np.zeros(nfig, dtype=np.int64)
        # the last values() of a long range: a report asks for every figure of the same ticks
        self._cache: tuple[int, int, np.ndarray] | None = None

    def offset(self, tick: int) -> int:
        """Where tick number ``tick``'s row starts in :attr:`buf`."""
        return (tick % self.window) * self.ncol

    def commit(self) -> None:
        """The row of tick number ``rows`` is complete."""
        rows = self.rows = self.rows + 1
        if rows >= self.window and rows % self._fold == 0:
            # the next rows to be overwritten leave the window: keep their extremes
            first = rows - self.window
            v = self._values(first, first + self._fold)
            valid = ~np.isnan(v)
            self.evicted_count += valid.sum(axis=0)
            self.evicted_min = np.fmin(self.evicted_min, np.where(valid, v, np.inf).min(axis=0))
            self.evicted_max = np.fmax(self.evicted_max, np.where(valid, v, -np.inf).max(axis=0))

    def oldest(self) -> int:
        """The oldest tick that can be read: the one before it shares its slot with the row being written."""
        return max(0, self.rows - self.window + 1)

    def values(self, start: int, stop: int) -> np.ndarray:
        """The figures (seconds) of committed ticks ``start`` .. ``stop - 1``, all still in the ring: one row per
        tick, the parts' durations (``nan`` where a part did not run), then lateness, duration and overrun."""
        if stop <= start:
            return np.empty((0, self.n_parts + 3))
        if stop - start == 1:
            return self._values(start, stop)
        # a report asks for every figure of nearly the same ticks: work out all committed rows once per tick
        first, rows = self.oldest(), self.rows
        cache = self._cache
        if cache is None or cache[0] != rows or cache[1] != first:
            cache = self._cache = (rows, first, self._values(first, rows))
        return cache[2][start - first : stop - first]

    def start_of(self, tick: int) -> float | None:
        """The start of tick number ``tick`` (committed or running), or None once its row has left the ring or
        before it began. Read from another thread: the row is checked to be still in the ring after the read."""
        if tick < 0 or tick >= self.begun:
            return None
        start = self.buf[self.offset(tick) + 1]
        return start if tick >= self.oldest() else None

    def lateness_of_running_tick(self) -> float | None:
        """Start minus deadline of the tick running now (its row is not committed yet), or None."""
        if self.begun <= self.rows:
            return None
        off = self.offset(self.rows)
        return self.buf[off + 1] - self.buf[off]

    def _values(self, start: int, stop: int) -> np.ndarray:
        m = np.frombuffer(self.buf, dtype=np.float64).reshape(self.window, self.ncol)
        rows = m[np.arange(start, stop) % self.window]
        times = rows[:, 1:-1]  # the start, then each part's end
        ran = ~np.isnan(times)
        latest = np.where(ran, np.arange(times.shape[1]), 0)
        np.maximum.accumulate(latest, axis=1, out=latest)
        before = np.take_along_axis(times, latest, axis=1)  # the nearest earlier time in the row
        out = np.empty((len(rows), self.n_parts + 3))
        out[:, : self.n_parts] = times[:, 1:] - before[:, :-1]
        out[:, self.LATENESS] = rows[:, 1] - rows[:, 0]
        duration = rows[:, -1] - rows[:, 1]
        out[:, self.TICK] = duration
        over = duration - self.period
        out[:, self.OVERRUN] = np.where(over > 1e-9, over, 0.0)
        return out


class TableSeries:
    """One figure of a :class:`TickTable` (a part's durations, or the loop's lateness, duration or overrun),
    read like a :class:`Series`.

    Samples are numbered by tick. A part's first tick is left out as in Donkeycar (one-off start-up costs: tick 1
    is its sample 0), and a tick that skipped the part has no sample (:meth:`at` returns ``None``). Lateness
    counts the tick running now (its start is known); duration and overrun count ended ticks.
    """

    __slots__ = ("col", "name", "running", "skip_first", "table")

    def __init__(self, name: str, table: TickTable, col: int, *, skip_first: bool, running: bool = False) -> None:
        self.name = name
        self.table = table
        self.col = col
        self.skip_first = skip_first
        self.running = running

    @property
    def count(self) -> int:
        t = self.table
        n = t.begun if self.running else t.rows
        return max(0, n - 1) if self.skip_first else n

    def at(self, n: int) -> float | None:
        """Sample number ``n``, or ``None`` (not recorded yet, left the window, or the part was skipped)."""
        t = self.table
        tick = n + 1 if self.skip_first else n
        if n < 0 or tick < t.oldest():
            return None
        if tick >= t.rows:
            return t.lateness_of_running_tick() if self.running and tick == t.rows else None
        v = float(t.values(tick, tick + 1)[0, self.col])
        return None if math.isnan(v) else v

    def count_at(self, rows: int) -> int:
        """:attr:`count` as it was when the table had ``rows`` committed rows (not for the running lateness): a
        recorder reads the row count once per tick instead of every part's count."""
        return max(0, rows - 1) if self.skip_first else rows

    def first_readable(self) -> int:
        """The oldest sample number whose row is still in the ring (see :meth:`Series.first_readable`)."""
        oldest = self.table.oldest()
        return max(0, oldest - 1) if self.skip_first else oldest

    @property
    def last(self) -> float | None:
        return self.at(self.count - 1) if self.count else None

    def recent(self, drop_last: bool = True) -> np.ndarray:
        """The samples of the ended ticks in the window, oldest first (the newest dropped when ``drop_last``)."""
        t = self.table
        first = max(1, t.oldest()) if self.skip_first else t.oldest()
        v: np.ndarray = t.values(first, t.rows - 1 if drop_last else t.rows)[:, self.col]
        kept: np.ndarray = v[~np.isnan(v)]
        return kept

    @property
    def max(self) -> float:
        return max(float(self.table.evicted_max[self.col]), float(self.recent(False).max(initial=-math.inf)))

    @property
    def min(self) -> float:
        return min(float(self.table.evicted_min[self.col]), float(self.recent(False).min(initial=math.inf)))

    def summary(self, drop_last: bool = True) -> dict[str, float] | None:
        arr = self.recent(drop_last)
        if len(arr) == 0:
            return None
        t = self.table
        count = int(t.evicted_count[self.col]) + len(self.recent(False))  # as Series.count: the newest included
        return _summary(arr, count, float(t.evicted_min[self.col]), float(t.evicted_max[self.col]))


class Profiler:
    """One :class:`Series` per part, the loop series (lateness, overrun, tick duration) and, per actuator,
    the sensing-to-actuation latency (the time a command reached the actuator's output minus the origin of the
    sensing behind it)."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        self.window = window
        self.parts: dict[str, Series | TableSeries] = {}
        self.latency: dict[str, Series] = {}
        self.lateness: Series | TableSeries = Series("tick lateness", window, skip_first=False)
        self.overrun: Series | TableSeries = Series("tick overrun", window, skip_first=False)
        self.tick: Series | TableSeries = Series("tick duration", window, skip_first=False)

    def use_table(self, table: TickTable) -> None:
        """Read the loop's series (lateness, overrun, tick duration) from a drive's :class:`TickTable`."""
        self.lateness = TableSeries("tick lateness", table, TickTable.LATENESS, skip_first=False, running=True)
        self.overrun = TableSeries("tick overrun", table, TickTable.OVERRUN, skip_first=False)
        self.tick = TableSeries("tick duration", table, TickTable.TICK, skip_first=False)

    def series_for(self, name: str) -> Series | TableSeries:
        """The part's series, made (a :class:`Series`) if it has none yet; a drive may have put its tick table's
        column (a :class:`TableSeries`) in its place."""
        s = self.parts.get(name)
        if s is None:
            s = self.parts[name] = Series(name, self.window)
        return s

    def latency_for(self, name: str) -> Series:
        s = self.latency.get(name)
        if s is None:
            s = self.latency[name] = Series(f"latency {name}", self.window, skip_first=False)
        return s

    def as_dict(self) -> dict[str, Any]:
        """Machine-readable report in ms: ``{"parts": {name: {max, min, avg, 50%, ...}}, "loop": {...},
        "latency": {actuator: {...}}}``."""
        return {
            "parts": {name: s.summary() for name, s in self.parts.items()},
            "latency": {name: s.summary(drop_last=False) for name, s in self.latency.items()},
            "loop": {
                "lateness": self.lateness.summary(drop_last=False),
                "overrun": self.overrun.summary(drop_last=False),
                "tick": self.tick.summary(drop_last=False),
            },
        }

    def table(self, extra_rows: Iterable[tuple[str, str]] = ()) -> str:
        """Donkeycar's report table (times in ms) with the loop rows underneath."""
        pt = PrettyTable()
        pt.field_names = ["part", "max", "min", "avg", *(_pct_key(p) for p in PERCENTILES)]
        for name, s in self.parts.items():
            _add_row(pt, name, s.summary())
        for s in (self.lateness, self.overrun, self.tick, *self.latency.values()):
            _add_row(pt, f"[{s.name}]", s.summary(drop_last=False))
        text = "Part Profile Summary: (times in ms)\n" + pt.get_string()
        for label, value in extra_rows:
            text += f"\n{label}: {value}"
        return text


def _add_row(pt: PrettyTable, name: str, summary: dict[str, float] | None) -> None:
    if summary is None:
        return
    pt.add_row(
        [
            name,
            *(f"{summary[k]:.2f}" for k in ("max", "min", "avg")),
            *(f"{summary[_pct_key(p)]:.2f}" for p in PERCENTILES),
        ]
    )
