"""The simulator as drive-loop parts: a camera, telemetry, and the car that takes ``angle`` and ``throttle``.

Wiring (camera and telemetry first, the actuator last, as on a real car)::

    car = SimCar()                                   # default track, respawn after 1 s off the road
    v.add(car.camera, outputs=["cam/image_array"])
    v.add(car.telemetry, outputs=list(TELEMETRY_OUTPUTS))
    ...                                              # controller, pilot, drive mode
    v.add(car, inputs=["angle", "throttle"])         # its async update() runs the simulation

How time works. The simulation follows the runtime clock (:func:`asyncdonkey.clock.get_clock`), so on the
virtual clock a test drives minutes of laps in a fraction of a second, deterministically. The physics is
integrated up to "now" whenever something observes or changes the car: each command from the tick (so a
command takes effect exactly when the tick gives it), each telemetry read, and each camera frame. It runs on
a grid of ``time_quantum`` (1 ms) counted from the task's start, so a drive is bit-identical whatever the
clock's absolute value, and long gaps are split into steps of at most ``max_step`` seconds so lap counting and
off-track detection never miss a crossing.

The camera frame is rendered by :meth:`SimCar.update`, a background task on deadlines ``t0 + k / camera_hz``,
and published into a :class:`~asyncdonkey.latest.Latest` like a real camera's newest frame; the camera part
returns the newest frame without waiting for one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from ...clock import Clock, DeadlineWaiter, get_clock
from ...latest import Latest
from .physics import clean_command
from .simulator import Simulator, Telemetry

__all__ = ["TELEMETRY_OUTPUTS", "SimCamera", "SimCar", "SimTelemetry"]

logger = logging.getLogger(__name__)

TELEMETRY_OUTPUTS: tuple[str, ...] = tuple(f"sim/{f}" for f in Telemetry._fields)
"""``sim/x, sim/y, sim/heading, sim/speed, sim/laps, sim/cte, sim/off_track`` — the order
:class:`SimTelemetry` returns them in."""


class SimCar:
    """The simulated car: actuator part (``run(angle, throttle)``) plus the simulation's background task.

    Args:
        sim: the simulation to run (default: ``Simulator(respawn_after_s=1.0)`` on the default track).
        camera_hz: camera frame rate (Donkeycar's ``CAMERA_FRAMERATE``, default 20).
        max_step: longest physics step in seconds when catching up to the clock (lap counting and off-track
            detection look at the car after each step).
        time_quantum: the simulation's time grid (s); commands take effect on it.

    Attributes:
        camera: the camera part (no inputs; output ``cam/image_array``).
        telemetry: the telemetry part (no inputs; outputs :data:`TELEMETRY_OUTPUTS`).
        frames: the :class:`~asyncdonkey.latest.Latest` the frames are published to.
        frames_rendered, frames_dropped: counts (dropped: camera deadlines skipped because the loop stalled).
    """

    def __init__(
        self,
        sim: Simulator | None = None,
        *,
        camera_hz: float = 20.0,
        max_step: float = 0.02,
        time_quantum: float = 0.001,
    ) -> None:
        if not (camera_hz > 0 and math.isfinite(camera_hz)):
            raise ValueError(f"SimCar: camera_hz must be a positive number, got {camera_hz!r}")
        if not 0 < time_quantum <= max_step:
            raise ValueError(
                f"SimCar: need 0 < time_quantum <= max_step (seconds), got {time_quantum!r} and {max_step!r}"
            )
        self.sim = sim if sim is not None else Simulator(respawn_after_s=1.0)
        self.camera_hz = float(camera_hz)
        self.max_step = float(max_step)
        self.frames: Latest[np.ndarray] = Latest()
        self.frames_rendered = 0
        self.frames_dropped = 0
        self.angle = 0.0
        self.throttle = 0.0
        self.time_quantum = float(time_quantum)
        self._chunk = max(1, round(max_step / time_quantum))
        self._clock: Clock | None = None
        self._anchor: float | None = None
        self._steps = 0
        self._running = False
        self.camera = SimCamera(self)
        self.telemetry = SimTelemetry(self)

    # --------------------------------------------------------------------------------- time keeping
    def _now(self) -> float:
        clock = self._clock
        if clock is None:
            clock = self._clock = get_clock()
        return clock.now()

    def advance_to(self, t: float) -> None:
        """Integrate the physics with the current command up to clock time ``t``.

        The simulation runs on a grid of ``time_quantum`` seconds counted from its anchor (the task's start),
        so the step sizes are exact multiples of the quantum whatever the clock's absolute value: a drive
        gives bit-identical results whether the clock starts at 0 or at 1e6.
        """
        if self._anchor is None:
            self._anchor = t
            return
        n = round((t - self._anchor) / self.time_quantum)
        k = n - self._steps
        if k <= 0:
            return
        step, q, chunk = self.sim.step, self.time_quantum, self._chunk
        full, rest = divmod(k, chunk)
        for _ in range(full):
            step(chunk * q, self.angle, self.throttle)
        if rest:
            step(rest * q, self.angle, self.throttle)
        self._steps = n

    # --------------------------------------------------------------------------------- part API
    def run(self, angle: Any, throttle: Any) -> None:
        """Take the tick's command (Donkeycar ranges: ``angle`` -1 left ... +1 right, ``throttle`` -1 ... +1).

        ``None`` (nothing written yet) is neutral; a non-number or NaN raises ``ValueError`` naming the input.
        """
        a = clean_command(angle, "SimCar input 'angle'")
        t = clean_command(throttle, "SimCar input 'throttle'")
        self.advance_to(self._now())
        self.angle = a
        self.throttle = t

    async def update(self) -> None:
        """Render camera frames on deadlines ``t0 + k / camera_hz``, advancing the physics to each."""
        clock = self._clock = get_clock()
        self._running = True
        t0 = clock.now()
        # (Re)anchor the simulation on this loop's clock: a new run may start on a new (virtual) clock.
        self._anchor, self._steps = t0, 0
        self._publish(t0)
        period_k = 1
        waiter = DeadlineWaiter()  # one OS timer for every frame
        try:
            while self._running:
                deadline = t0 + period_k / self.camera_hz
                await waiter.wait_until(deadline)
                now = clock.now()
                due = math.floor((now - t0) * self.camera_hz + 1e-9)
                if due > period_k:
                    # the loop stalled: render only the newest frame, as a real camera's buffer would
                    self.frames_dropped += due - period_k
                    period_k = due
                    deadline = t0 + period_k / self.camera_hz
                self.advance_to(deadline)
                self._publish(deadline)
                period_k += 1
        finally:
            waiter.close()
            self._running = False

    def _publish(self, t: float) -> None:
        self.frames.publish(self.sim.render(), t)
        self.frames_rendered += 1

    def safe_state_sync(self) -> None:
        """The simulated ESC's safe state: throttle 0 (the car rolls to a stop). Any thread."""
        self.throttle = 0.0

    def shutdown(self) -> None:
        """Stop the simulation task after its current frame; the car coasts no further."""
        self.throttle = 0.0
        self._running = False

    def __repr__(self) -> str:
        return f"SimCar({self.sim!r}, camera_hz={self.camera_hz})"


class SimCamera:
    """Camera part: ``run()`` returns the newest frame ``(120, 160, 3)`` uint8 RGB (output ``cam/image_array``).

    Before the car's task has published anything (or if the :class:`SimCar` was not added to the vehicle),
    the frame is rendered on the spot, so the first tick never sees ``None`` — a ``None`` camera frame during
    warm-up is a classic way for a Donkeycar pilot to crash.
    """

    def __init__(self, car: SimCar) -> None:
        self.car = car
        self._origin: float | None = None

    def run(self) -> np.ndarray:
        sample = self.car.frames.sample
        if sample is None:
            car = self.car
            now = car._now()
            car.advance_to(now)
            car._publish(now)
            sample = car.frames.sample
            assert sample is not None
        self._origin = sample.timestamp
        return sample.value

    def output_origin(self) -> float | None:
        """The render time of the frame ``run()`` returned (the simulated capture)."""
        return self._origin

    def subscribe(self, callback: Callable[[np.ndarray, float], None]) -> Callable[[], None]:
        """Push each frame as it is rendered (a pipelined pilot with ``trigger`` starts on it at once)."""
        return self.car.frames.subscribe(callback)

    def age(self) -> float:
        """Seconds since the newest frame was taken, on the runtime clock (``inf`` before the first)."""
        return self.car.frames.age(self.car._now())


class SimTelemetry:
    """Telemetry part: ``run()`` returns :class:`~.simulator.Telemetry` for the outputs :data:`TELEMETRY_OUTPUTS`.

    The physics is first advanced to now, so the pose is that of this tick, not of the last frame.
    """

    def __init__(self, car: SimCar) -> None:
        self.car = car

    def run(self) -> Telemetry:
        car = self.car
        car.advance_to(car._now())
        return car.sim.telemetry()
