"""The loop's health in a few numbers for the page's status strip, from the drive's profiler.

What a driver wants to see at a glance: is the loop keeping its rate, is it late, which part is slow, and how
long a command takes from the moment it was sensed (for the web controller: when it reached the car) to the
PWM write (the profiler's sensing-to-actuation latency per actuator). All over the last ``ticks`` ticks.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["vehicle_health"]


def _pcts(samples: np.ndarray) -> dict[str, float] | None:
    if len(samples) == 0:
        return None
    p50, p99 = np.percentile(samples, (50, 99))
    return {"p50_ms": round(float(p50) * 1e3, 3), "p99_ms": round(float(p99) * 1e3, 3)}


def vehicle_health(vehicle: Any, ticks: int = 200) -> dict[str, Any]:
    """``lateness`` (p50/p99 ms), ``parts`` (name → p50/p99 ms), ``latency`` (actuator → p50/p99 ms), ``ticks``."""
    prof = vehicle.profiler
    late = prof.lateness.recent(drop_last=False)[-ticks:]
    parts = {}
    for name, series in prof.parts.items():
        p = _pcts(series.recent(drop_last=False)[-ticks:])
        if p is not None:
            parts[name] = p
    latency = {}
    for name, series in prof.latency.items():
        p = _pcts(series.recent(drop_last=False)[-ticks:])
        if p is not None:
            latency[name] = p
    return {"ticks": int(prof.lateness.count), "lateness": _pcts(late), "parts": parts, "latency": latency}
