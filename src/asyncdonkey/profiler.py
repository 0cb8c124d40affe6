"""Per-part and per-tick timing with bounded memory, reported in Donkeycar's format.

Donkeycar's profiler appends every sample to a list for the whole drive, so hours of driving grow it without
bound. Here each series keeps the most recent ``window`` samples in a fixed ``array('d')`` ring (percentiles
and averages come from that window) plus run-long count, min and max. As in Donkeycar, the first sample of each
part is ignored (one-off start-up cost) and so is the last (it may have been cut short by a stop).

Recording one sample is an index computation and one store: it sits on the hot path for every part of every
tick.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterable
from typing import Any

import numpy as np
from prettytable import PrettyTable

__all__ = ["DEFAULT_WINDOW", "PERCENTILES", "Profiler", "Series"]

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
        pct = np.percentile(arr, PERCENTILES)
        out = {
            "max": float(arr.max()) * 1e3,
            "min": float(arr.min()) * 1e3,
            "avg": float(arr.mean()) * 1e3,
            "count": float(self.count),
        }
        for p, v in zip(PERCENTILES, pct, strict=True):
            out[_pct_key(p)] = float(v) * 1e3
        if self.count > self.window:  # run-long extremes reach beyond the window
            out["max"] = max(out["max"], self.evicted_max * 1e3)
            out["min"] = min(out["min"], self.evicted_min * 1e3)
        return out


def _pct_key(p: float) -> str:
    return f"{p:g}%"


class Profiler:
    """One :class:`Series` per part, the loop series (lateness, overrun, tick duration) and, per actuator,
    the sensing-to-actuation latency (the time a command reached the actuator's output minus the origin of the
    sensing behind it)."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        self.window = window
        self.parts: dict[str, Series] = {}
        self.latency: dict[str, Series] = {}
        self.lateness = Series("tick lateness", window, skip_first=False)
        self.overrun = Series("tick overrun", window, skip_first=False)
        self.tick = Series("tick duration", window, skip_first=False)

    def series_for(self, name: str) -> Series:
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
