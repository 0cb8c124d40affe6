"""Track geometry: a closed road of known width around a centre line, and lap counting on it.

The centre line is a closed polyline resampled to (nearly) equal spacing, with the arc length ``s`` of each
vertex. Everything the simulator needs follows from it: where a point is along the road and how far it is
from the centre (:meth:`Track.project`), the pose at an arc length (:meth:`Track.pose_at`) and, drawn into a
top-down texture, what the camera sees (:mod:`.render`).

Conventions (used throughout :mod:`asyncdonkey.parts.sim`):

* World coordinates in metres, ``x`` east, ``y`` north; headings in radians counter-clockwise from ``+x``.
* The road is driven in the direction of increasing ``s``; the start/finish line is at ``s = 0``.
* Cross-track error is **positive to the right** of the centre line (looking along the road), matching
  Donkeycar's steering sign (``angle > 0`` steers right). A car right of the line corrects with ``angle < 0``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["LapCounter", "Projection", "Track", "default_track"]


@dataclass(frozen=True, slots=True)
class Projection:
    """Where a point lies relative to the centre line.

    Attributes:
        s: arc length of the nearest centre-line point, in ``[0, length)``.
        cte: signed distance to the centre line, positive to the right of the direction of travel.
        heading: direction of the road at ``s`` (radians).
    """

    s: float
    cte: float
    heading: float


class Track:
    """A closed road: centre line (``(N, 2)`` metres, not repeating the first point) and total ``width``.

    The centre line is resampled to equal spacing so arc length is proportional to the vertex index; that
    makes :meth:`point_at` a constant-time lookup.
    """

    def __init__(
        self,
        centre: np.ndarray | Sequence[Sequence[float]],
        width: float,
        *,
        spacing: float = 0.05,
        name: str = "track",
    ) -> None:
        pts = np.asarray(centre, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
            raise ValueError(f"Track {name!r}: centre must be an (N, 2) array of N >= 3 points, got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"Track {name!r}: centre has non-finite coordinates")
        if not (width > 0 and math.isfinite(width)):
            raise ValueError(f"Track {name!r}: width must be a positive number of metres, got {width!r}")
        if not spacing > 0:
            raise ValueError(f"Track {name!r}: spacing must be positive, got {spacing!r}")
        if np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]
        self.name = name
        self.width = float(width)
        self.half_width = self.width / 2.0
        self.points = _resample_closed(pts, spacing)
        nxt = np.roll(self.points, -1, axis=0)
        self._seg = nxt - self.points
        self._seg_len = np.hypot(self._seg[:, 0], self._seg[:, 1])
        self._seg_len2 = self._seg_len**2
        self._seg_dir = self._seg / self._seg_len[:, None]
        self.s = np.concatenate(([0.0], np.cumsum(self._seg_len)))[:-1]
        """Arc length at each vertex of :attr:`points`."""
        self.length = float(self._seg_len.sum())
        self.headings = np.arctan2(self._seg[:, 1], self._seg[:, 0])
        """Direction of each segment (from vertex ``i`` to ``i + 1``)."""

    # ------------------------------------------------------------------------------ constructors
    @classmethod
    def from_control_points(
        cls, control: Sequence[Sequence[float]], width: float, *, spacing: float = 0.05, name: str = "spline"
    ) -> Track:
        """A smooth closed road through ``control`` points (a periodic centripetal Catmull-Rom spline)."""
        return cls(_catmull_rom_closed(np.asarray(control, dtype=np.float64)), width, spacing=spacing, name=name)

    @classmethod
    def oval(cls, straight: float = 8.0, radius: float = 3.0, width: float = 1.0, *, spacing: float = 0.05) -> Track:
        """Two straights of length ``straight`` joined by half circles of ``radius``, driven anticlockwise.

        The start line is at the beginning of the bottom straight (``(-straight/2, -radius)``, heading east).
        """
        return cls.rounded_rectangle(straight + 2 * radius, 2 * radius, radius, width, spacing=spacing)

    @classmethod
    def rounded_rectangle(
        cls, length: float, breadth: float, corner_radius: float, width: float = 1.0, *, spacing: float = 0.05
    ) -> Track:
        """A ``length`` x ``breadth`` rectangle (centre line) with rounded corners, driven anticlockwise.

        Centred on the origin; the start line is at the beginning of the bottom straight, heading east, so a
        long ``length`` gives a long straight road ahead of the start pose.
        """
        r = float(corner_radius)
        if not (0 < r <= min(length, breadth) / 2):
            raise ValueError(f"rounded_rectangle: corner_radius must be in (0, {min(length, breadth) / 2}], got {r}")
        hx, hy = length / 2 - r, breadth / 2 - r
        step = spacing / 4
        pieces: list[np.ndarray] = []
        # Corners centred at (±hx, ±hy), visited anticlockwise starting from the bottom straight.
        for cx, cy, a0 in ((hx, -hy, -math.pi / 2), (hx, hy, 0.0), (-hx, hy, math.pi / 2), (-hx, -hy, math.pi)):
            # straight leading into this corner
            start = pieces[-1][-1] if pieces else np.array([-hx, -hy - r])
            end = np.array([cx + r * math.cos(a0), cy + r * math.sin(a0)])
            n = max(2, int(np.hypot(*(end - start)) / step))
            pieces.append(np.linspace(start, end, n, endpoint=False))
            m = max(4, int(r * math.pi / 2 / step))
            a = a0 + np.linspace(0, math.pi / 2, m, endpoint=False)
            pieces.append(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1))
            pieces.append(np.array([[cx + r * math.cos(a0 + math.pi / 2), cy + r * math.sin(a0 + math.pi / 2)]]))
        pts = np.concatenate(pieces)
        return cls(pts, width, spacing=spacing, name="rounded_rectangle")

    # ------------------------------------------------------------------------------ queries
    def project(self, x: float, y: float) -> Projection:
        """Nearest point of the centre line to ``(x, y)``: arc length, signed cross-track error, road heading."""
        px = x - self.points[:, 0]
        py = y - self.points[:, 1]
        t = (px * self._seg[:, 0] + py * self._seg[:, 1]) / self._seg_len2
        np.clip(t, 0.0, 1.0, out=t)
        dx = px - t * self._seg[:, 0]
        dy = py - t * self._seg[:, 1]
        d2 = dx * dx + dy * dy
        i = int(np.argmin(d2))
        ti = float(t[i])
        ux, uy = self._seg_dir[i]
        # cross(direction, offset) > 0 means left of the road; the convention here is right-positive.
        cross = ux * float(dy[i]) - uy * float(dx[i])
        dist = math.sqrt(float(d2[i]))
        cte = -dist if cross > 0 else dist
        s = float(self.s[i]) + ti * float(self._seg_len[i])
        if s >= self.length:
            s -= self.length
        return Projection(s, cte, float(self.headings[i]))

    def point_at(self, s: float) -> tuple[float, float]:
        """Centre-line point at arc length ``s`` (any real ``s``; it wraps around the lap)."""
        i, t = self._locate(s)
        p = self.points[i] + t * self._seg[i]
        return float(p[0]), float(p[1])

    def heading_at(self, s: float) -> float:
        """Road direction at arc length ``s`` (radians)."""
        i, _ = self._locate(s)
        return float(self.headings[i])

    def pose_at(self, s: float, offset: float = 0.0) -> tuple[float, float, float]:
        """``(x, y, heading)`` at arc length ``s``, ``offset`` metres to the right of the centre line."""
        i, t = self._locate(s)
        p = self.points[i] + t * self._seg[i]
        ux, uy = self._seg_dir[i]
        # right of direction (ux, uy) is (uy, -ux)
        return float(p[0] + offset * uy), float(p[1] - offset * ux), float(self.headings[i])

    def curvature_at(self, s: float, span: float = 0.5) -> float:
        """Signed curvature (1/m, positive turning left) averaged over ``span`` metres around ``s``."""
        h0 = self.heading_at(s - span / 2)
        h1 = self.heading_at(s + span / 2)
        return wrap_angle(h1 - h0) / span

    def bounds(self, margin: float = 0.0) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of the road (centre line ± half width) plus ``margin`` metres."""
        lo = self.points.min(axis=0) - self.half_width - margin
        hi = self.points.max(axis=0) + self.half_width + margin
        return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])

    def min_radius(self) -> float:
        """The tightest turn radius of the centre line (metres), measured over 0.5 m spans."""
        dh = np.abs(wrap_angle(np.roll(self.headings, -1) - self.headings))
        k = np.convolve(np.concatenate((dh[-10:], dh, dh[:10])), np.ones(10), mode="same")[10:-10]
        span = 10 * float(self._seg_len.mean())
        kmax = float(k.max()) / span
        return math.inf if kmax == 0 else 1.0 / kmax

    def _locate(self, s: float) -> tuple[int, float]:
        s = s % self.length
        i = int(np.searchsorted(self.s, s, side="right")) - 1
        i = min(max(i, 0), len(self.s) - 1)
        return i, (s - float(self.s[i])) / float(self._seg_len[i])

    def __repr__(self) -> str:
        return f"Track({self.name!r}, length={self.length:.2f} m, width={self.width:.2f} m)"


class LapCounter:
    """Counts laps from successive arc lengths ``s`` on a track of ``length``.

    Progress is the unwrapped arc length: each update adds the change in ``s`` wrapped to ± half a lap, so
    driving backwards subtracts. A lap is counted when the car crosses the start line (``s = 0``) going
    forward **onto new ground** (progress beyond anything reached before) **having driven at least**
    ``min_fraction`` **of a lap since the last lap was counted** (net distance: reversing subtracts). Hence:

    * jitter back and forth across the line counts once;
    * reversing over the line and driving forward over it again counts nothing;
    * a car placed just behind the line does not score a lap by rolling over it: as in a race, that crossing
      starts lap 1. The default start pose is just past the line, so lap 1 is one full lap.

    An update that moves more than ``max_jump`` metres is not driving (a teleport, or the projection of a car
    far off the road jumping to another part of the track): it moves the car without crediting distance, and
    :meth:`jump` does the same on purpose.
    """

    __slots__ = ("best", "credit", "laps", "length", "max_jump", "min_credit", "progress", "s")

    def __init__(self, length: float, s0: float = 0.0, *, max_jump: float = 2.0, min_fraction: float = 0.5) -> None:
        if not length > 0:
            raise ValueError(f"LapCounter: length must be positive, got {length!r}")
        if not 0 <= min_fraction <= 1:
            raise ValueError(f"LapCounter: min_fraction must be in [0, 1], got {min_fraction!r}")
        self.length = float(length)
        self.max_jump = float(max_jump)
        self.min_credit = float(min_fraction) * self.length
        self.reset(s0)

    def reset(self, s0: float = 0.0) -> None:
        """Start counting afresh with the car at ``s0``: no laps, no distance driven."""
        self.s = float(s0) % self.length
        self.progress = self.s
        self.best = self.progress
        self.credit = 0.0
        self.laps = 0

    def jump(self, s: float) -> None:
        """The car was moved to ``s`` without driving there: keep the laps, credit nothing."""
        s = float(s) % self.length
        # re-anchor on the nearest unwrapped position to where the car was, so progress stays continuous
        k = round((self.progress - s) / self.length)
        self.progress = k * self.length + s
        self.s = s
        self.credit = 0.0
        if self.progress > self.best:
            self.best = self.progress

    def update(self, s: float) -> int:
        """Feed the car's current arc length; returns the lap count."""
        s = float(s) % self.length
        ds = s - self.s
        half = self.length / 2
        if ds > half:
            ds -= self.length
        elif ds < -half:
            ds += self.length
        if abs(ds) > self.max_jump:
            self.jump(s)
            return self.laps
        self.s = s
        before = self.progress
        after = before + ds
        self.progress = after
        self.credit += ds
        if after > self.best:
            self.best = after
            line = math.floor(after / self.length) * self.length
            if before < line <= after:
                if self.credit >= self.min_credit:
                    self.laps += 1
                self.credit = after - line
        return self.laps


def wrap_angle(a):  # type: ignore[no-untyped-def]
    """Wrap an angle (or array of angles) to ``[-pi, pi)``."""
    return (a + math.pi) % (2 * math.pi) - math.pi


def default_track(width: float = 1.0, spacing: float = 0.05) -> Track:
    """The simulator's standard circuit: about 45 m with left and right turns of different radii.

    Driven anticlockwise overall; the inward bend on the north side is a right-hander, so a pilot trained
    here sees turns in both directions. Tightest radius about 2 m (the car can turn in 0.56 m).
    """
    control = [
        (0.0, 0.0),
        (5.0, 0.0),
        (9.0, 0.2),
        (12.0, 1.8),
        (12.6, 5.0),
        (11.0, 8.0),
        (8.0, 8.4),
        (6.0, 6.8),
        (4.0, 6.2),
        (1.5, 7.6),
        (-1.5, 7.8),
        (-3.4, 5.8),
        (-3.6, 2.6),
        (-2.6, 0.6),
    ]
    t = Track.from_control_points(control, width, spacing=spacing, name="default")
    return t


# ---------------------------------------------------------------------------------- internals
def _catmull_rom_closed(ctrl: np.ndarray, samples_per_span: int = 200) -> np.ndarray:
    """Dense points on the periodic centripetal Catmull-Rom spline through ``ctrl`` (no cusps or loops)."""
    n = len(ctrl)
    if n < 3:
        raise ValueError(f"a closed spline needs at least 3 control points, got {n}")
    out = []
    u = np.linspace(0.0, 1.0, samples_per_span, endpoint=False)[:, None]
    for i in range(n):
        p0, p1, p2, p3 = ctrl[(i - 1) % n], ctrl[i], ctrl[(i + 1) % n], ctrl[(i + 2) % n]
        t0 = 0.0
        t1 = t0 + max(np.linalg.norm(p1 - p0), 1e-9) ** 0.5
        t2 = t1 + max(np.linalg.norm(p2 - p1), 1e-9) ** 0.5
        t3 = t2 + max(np.linalg.norm(p3 - p2), 1e-9) ** 0.5
        t = t1 + u * (t2 - t1)
        a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
        a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
        a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
        b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
        b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
        out.append((t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2)
    return np.concatenate(out)


def _resample_closed(pts: np.ndarray, spacing: float) -> np.ndarray:
    """Resample a closed polyline to equal arc-length spacing (as close to ``spacing`` as divides the lap)."""
    closed = np.vstack([pts, pts[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    keep = np.concatenate(([True], seg > 1e-12))
    closed = closed[keep]
    s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(closed, axis=0).T))))
    total = s[-1]
    n = max(8, round(total / spacing))
    q = np.linspace(0.0, total, n, endpoint=False)
    return np.stack([np.interp(q, s, closed[:, 0]), np.interp(q, s, closed[:, 1])], axis=1)
