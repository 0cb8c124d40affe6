"""The simulated car without any event loop: ``step(dt, angle, throttle)`` and ``render()``.

:class:`Simulator` ties a :class:`~.track.Track`, a :class:`~.physics.BicycleModel`, lap counting and the
camera together. It is synchronous and deterministic, so data collection and training scripts can drive it
as fast as the CPU allows; the drive-loop parts in :mod:`.parts` wrap one instance and step it on the
runtime clock.
"""

from __future__ import annotations

import math
import threading
import weakref
from typing import NamedTuple

import numpy as np

from .physics import BicycleModel, CarParams, CarState
from .render import CameraRenderer, CameraSpec, TrackTexture
from .track import LapCounter, Track, default_track

__all__ = ["Simulator", "Telemetry"]


class Telemetry(NamedTuple):
    """What the simulator reports; field order matches :data:`asyncdonkey.parts.sim.TELEMETRY_OUTPUTS`.

    Attributes:
        x, y: rear-axle position (m). heading: radians anticlockwise from east. speed: m/s (negative reversing).
        laps: completed laps (see :class:`~.track.LapCounter`). cte: cross-track error (m, positive right of
        the centre line). off_track: ``abs(cte)`` exceeds half the road width.
    """

    x: float
    y: float
    heading: float
    speed: float
    laps: int
    cte: float
    off_track: bool


_TEXTURES: weakref.WeakKeyDictionary[Track, dict[tuple[float, int], TrackTexture]] = weakref.WeakKeyDictionary()
_TEXTURES_LOCK = threading.Lock()


def shared_texture(track: Track, resolution: float = 0.02, seed: int = 0) -> TrackTexture:
    """The texture of ``track`` (built once per track object, resolution and seed, then shared).

    Drawing it takes a few hundred milliseconds; several simulators on one track (tests, data collection in
    a loop) should not pay that each time. Textures are read-only after construction.
    """
    with _TEXTURES_LOCK:
        per_track = _TEXTURES.setdefault(track, {})
        tex = per_track.get((resolution, seed))
        if tex is None:
            tex = per_track[(resolution, seed)] = TrackTexture(track, resolution=resolution, seed=seed)
        return tex


class Simulator:
    """A car on a track. Not thread-safe: one owner steps it (the :class:`~.parts.SimCar` task, or a script).

    Args:
        track: the road (default: :func:`~.track.default_track`).
        params: the car (default: :class:`~.physics.CarParams`).
        camera: the camera (default: :class:`~.render.CameraSpec`, 160x120).
        start_s: arc length of the start pose (default just past the start line).
        respawn_after_s: after this long off the road, put the car back on the centre line at the nearest
            point, stopped and facing along the road (``None``: never; it drives on over the grass).
        texture_seed: seed of the grass/asphalt noise.
    """

    def __init__(
        self,
        track: Track | None = None,
        params: CarParams | None = None,
        camera: CameraSpec | None = None,
        *,
        start_s: float = 0.05,
        respawn_after_s: float | None = None,
        texture_seed: int = 0,
    ) -> None:
        self.track = track if track is not None else default_track()
        self.model = BicycleModel(params)
        self.camera_spec = camera or CameraSpec()
        self.respawn_after_s = respawn_after_s
        self._texture_seed = texture_seed
        self._renderer: CameraRenderer | None = None
        self.time = 0.0
        """Simulated seconds since the last :meth:`reset`."""
        self.respawns = 0
        self.reset(start_s)

    @property
    def params(self) -> CarParams:
        return self.model.params

    @property
    def renderer(self) -> CameraRenderer:
        """Built on first use, so physics-only users never draw a texture."""
        if self._renderer is None:
            self._renderer = CameraRenderer(shared_texture(self.track, seed=self._texture_seed), self.camera_spec)
        return self._renderer

    def reset(self, s: float = 0.05, offset: float = 0.0, heading_error: float = 0.0, speed: float = 0.0) -> Telemetry:
        """Start afresh (time, laps, respawns zeroed) with the car at arc length ``s``, ``offset`` m right of
        the centre, turned ``heading_error`` rad (positive: to the left of the road direction), at ``speed``."""
        x, y, h = self.track.pose_at(s, offset)
        self.state = CarState(x, y, h + heading_error, speed, 0.0)
        proj = self.track.project(x, y)
        self.laps = LapCounter(self.track.length, proj.s)
        self.time = 0.0
        self.respawns = 0
        self._cte = proj.cte
        self._off_since: float | None = None
        return self.telemetry()

    def set_pose(self, x: float, y: float, heading: float, speed: float = 0.0) -> Telemetry:
        """Move the car, keeping time and laps; the move itself is not driving, so it earns no lap credit."""
        self.state = CarState(x, y, heading, speed, self.state.steer)
        proj = self.track.project(x, y)
        self.laps.jump(proj.s)
        self._cte = proj.cte
        self._off_since = None
        return self.telemetry()

    def _respawn(self, s: float) -> None:
        """Back on the centre line at ``s`` (where the car left the road), stopped, facing along the road.

        The lap counter already stands at ``s``, so the distance driven before leaving the road still counts.
        """
        x, y, h = self.track.pose_at(s)
        self.state = CarState(x, y, h, 0.0, 0.0)
        self._cte = 0.0
        self._off_since = None
        self.respawns += 1

    def step(self, dt: float, angle: float | None, throttle: float | None) -> Telemetry:
        """Advance ``dt`` seconds holding ``angle`` and ``throttle`` (Donkeycar's [-1, 1]; ``None`` = 0)."""
        self.state = self.model.step(self.state, angle, throttle, dt)  # type: ignore[arg-type]
        self.time += dt
        st = self.state
        proj = self.track.project(st.x, st.y)
        self.laps.update(proj.s)
        self._cte = proj.cte
        if abs(proj.cte) > self.track.half_width:
            if self._off_since is None:
                self._off_since = self.time
            elif self.respawn_after_s is not None and self.time - self._off_since >= self.respawn_after_s:
                self._respawn(proj.s)
        else:
            self._off_since = None
        return self.telemetry()

    def telemetry(self) -> Telemetry:
        st = self.state
        return Telemetry(
            st.x, st.y, st.heading, st.speed, self.laps.laps, self._cte, abs(self._cte) > self.track.half_width
        )

    @property
    def cte(self) -> float:
        return self._cte

    @property
    def progress(self) -> float:
        """Unwrapped distance along the road since the start line (m); reversing subtracts."""
        return self.laps.progress

    def render(self) -> np.ndarray:
        """The camera image at the current pose: ``(120, 160, 3)`` uint8 RGB, a new array each call."""
        st = self.state
        return self.renderer.render(st.x, st.y, st.heading)

    def __repr__(self) -> str:
        st = self.state
        return (
            f"Simulator({self.track.name}, t={self.time:.2f}s, x={st.x:.2f}, y={st.y:.2f}, "
            f"heading={math.degrees(st.heading):.1f}°, speed={st.speed:.2f}, laps={self.laps.laps})"
        )
