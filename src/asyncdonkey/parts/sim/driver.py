"""A scripted "user": pure pursuit on the known centre line, with a little human-like wobble.

It stands in for a person with a joystick when recording training sessions in the simulator: it sees the
true pose (``sim/x``, ``sim/y``, ``sim/heading``) rather than the camera image, steers towards a point
``lookahead`` metres further along the centre line, slows down for bends, and adds slowly varying noise to
the steering (an Ornstein-Uhlenbeck process), so recorded sessions are not robotically perfect.

Pure pursuit: with the target point at distance ``d`` and lateral offset ``lat`` (left positive) in the
car's frame, the arc through it has curvature ``2 · lat / d²``; a kinematic bicycle referenced at the rear
axle follows that arc with wheel angle ``atan(wheelbase · curvature)``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .physics import CarParams
from .track import Track

__all__ = ["ScriptedDriver"]


class ScriptedDriver:
    """Part: inputs ``sim/x, sim/y, sim/heading`` → outputs ``user/angle, user/throttle``.

    Args:
        track: the road to follow.
        params: the car it drives (for wheelbase and steering limit).
        lookahead: pure-pursuit look-ahead distance along the centre line (m).
        throttle: throttle on straights; ``corner_throttle`` in the tightest bends (linear in between).
        noise: standard deviation of the steering wobble (in Donkeycar angle units).
        noise_tau: correlation time of the wobble (s).
        rate_hz: how often ``run`` is called (the drive loop rate), for the wobble's time scale.
        seed: random seed, so a recorded session is reproducible.
    """

    def __init__(
        self,
        track: Track,
        params: CarParams | None = None,
        *,
        lookahead: float = 0.8,
        throttle: float = 0.5,
        corner_throttle: float = 0.35,
        noise: float = 0.04,
        noise_tau: float = 0.6,
        rate_hz: float = 20.0,
        seed: int | None = 0,
    ) -> None:
        if not lookahead > 0:
            raise ValueError(f"ScriptedDriver: lookahead must be positive metres, got {lookahead!r}")
        if not rate_hz > 0:
            raise ValueError(f"ScriptedDriver: rate_hz must be positive, got {rate_hz!r}")
        self.track = track
        self.params = params or CarParams()
        self.lookahead = float(lookahead)
        self.throttle = float(throttle)
        self.corner_throttle = float(corner_throttle)
        self.noise = float(noise)
        self._a = math.exp(-1.0 / (rate_hz * noise_tau)) if noise_tau > 0 else 0.0
        self._b = self.noise * math.sqrt(1.0 - self._a**2)
        self._rng = np.random.default_rng(seed)
        self._wobble = 0.0
        # the bend that needs corner_throttle: the tightest the track has
        self._kmax = 1.0 / max(track.min_radius(), 1e-6)

    def expert(self, x: float, y: float, heading: float) -> tuple[float, float]:
        """The noiseless command for a pose: ``(angle, throttle)``. Also the label for recovery data."""
        tr = self.track
        proj = tr.project(x, y)
        tx, ty = tr.point_at(proj.s + self.lookahead)
        dx, dy = tx - x, ty - y
        c, s = math.cos(heading), math.sin(heading)
        fwd = c * dx + s * dy
        lat = -s * dx + c * dy  # left positive
        d2 = max(dx * dx + dy * dy, 1e-6)
        if fwd < 0:
            # target behind (car turned round): full lock towards it
            lat = math.copysign(max(abs(lat), 1.0), lat if lat != 0 else 1.0)
        kappa = 2.0 * lat / d2
        wheel = math.atan(self.params.wheelbase * kappa)  # positive = left
        angle = max(-1.0, min(1.0, -wheel / self.params.max_steer))
        bend = min(1.0, abs(tr.curvature_at(proj.s + self.lookahead, span=1.0)) / self._kmax)
        throttle = self.throttle + (self.corner_throttle - self.throttle) * bend
        return angle, throttle

    def run(self, x: Any, y: Any, heading: Any) -> tuple[float, float]:
        if x is None or y is None or heading is None:
            return 0.0, 0.0
        angle, throttle = self.expert(float(x), float(y), float(heading))
        if self.noise > 0:
            self._wobble = self._a * self._wobble + self._b * float(self._rng.standard_normal())
            angle = max(-1.0, min(1.0, angle + self._wobble))
        return angle, throttle
