"""Kinematic bicycle model of a 1/10 scale car: throttle → speed through a first-order motor, steering limits.

Why kinematic and not dynamic: at Donkeycar speeds (a few m/s, no drifting) tyre slip is small, and a
kinematic model has no stiff tyre forces, so it is stable with a modest fixed sub-step and cheap enough to run
at 100 Hz beside the drive loop. The reference point is the rear axle, so ``heading`` changes at
``speed · tan(steer) / wheelbase`` and a pure-pursuit controller applies without correction.

Motor: the speed follows a first-order response towards ``throttle · max_speed`` with time constant
``motor_tau`` (an electric motor's force minus a drag proportional to speed, solved exactly over each
sub-step). Reverse is limited to ``reverse_ratio · max_speed``, like an ESC's reverse limit.

Steering: Donkeycar's ``angle`` in ``[-1, 1]`` (positive steers **right**) maps to a wheel angle of
``angle · max_steer``; the wheels move towards it no faster than ``steer_rate`` (a servo's speed).

Determinism: :meth:`BicycleModel.step` splits ``dt`` into ``ceil(dt / substep)`` equal sub-steps and uses only
float arithmetic on its inputs, so the same command sequence and ``dt`` give bit-identical states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["BicycleModel", "CarParams", "CarState", "clean_command"]


@dataclass(frozen=True, slots=True)
class CarParams:
    """Physical parameters (SI units, degrees where the name says so). Defaults: a 1/10 scale Donkey car."""

    wheelbase: float = 0.26
    max_steer_deg: float = 25.0
    steer_rate_deg_s: float = 400.0
    """Servo speed; ``math.inf`` for instant steering."""
    max_speed: float = 4.0
    """Steady-state speed at full forward throttle (m/s)."""
    reverse_ratio: float = 0.5
    motor_tau: float = 0.5
    """Time constant of the speed response (s): about 63 % of a throttle step's speed change after this long."""
    substep: float = 0.005
    """Longest integration step (s)."""

    def __post_init__(self) -> None:
        for name in ("wheelbase", "max_steer_deg", "steer_rate_deg_s", "max_speed", "motor_tau", "substep"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and v > 0):
                raise ValueError(f"CarParams.{name} must be a positive number, got {v!r}")
        if not 0 < self.max_steer_deg < 90:
            raise ValueError(f"CarParams.max_steer_deg must be in (0, 90), got {self.max_steer_deg!r}")
        if not 0 <= self.reverse_ratio <= 1:
            raise ValueError(f"CarParams.reverse_ratio must be in [0, 1], got {self.reverse_ratio!r}")

    @property
    def max_steer(self) -> float:
        """Largest wheel angle (radians)."""
        return math.radians(self.max_steer_deg)

    @property
    def min_turn_radius(self) -> float:
        """Radius of the tightest turn at full lock (metres, rear axle)."""
        return self.wheelbase / math.tan(self.max_steer)


@dataclass(frozen=True, slots=True)
class CarState:
    """Pose and motion. ``steer`` is the actual wheel angle in radians, positive to the right."""

    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0
    speed: float = 0.0
    steer: float = 0.0


def clean_command(value: object, what: str) -> float:
    """A command as a float in ``[-1, 1]``; ``None`` (nothing written yet) means neutral.

    Raises ``ValueError`` naming ``what`` for anything that is not a finite number: a NaN steering command
    must stop the car loudly, not be driven.
    """
    if value is None:
        return 0.0
    try:
        f = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected a number in [-1, 1], got {type(value).__name__} {value!r}") from None
    if not math.isfinite(f):
        raise ValueError(f"{what}: expected a finite number in [-1, 1], got {f!r}")
    return -1.0 if f < -1.0 else (1.0 if f > 1.0 else f)


class BicycleModel:
    """Advances a :class:`CarState` under constant commands for ``dt`` seconds."""

    __slots__ = ("_cache", "params")

    def __init__(self, params: CarParams | None = None) -> None:
        self.params = params or CarParams()
        self._cache: dict[float, tuple[int, float, float, float]] = {}

    def _plan(self, dt: float) -> tuple[int, float, float, float]:
        """Sub-step count, length, motor decay factor and steering travel per sub-step for ``dt`` (cached)."""
        plan = self._cache.get(dt)
        if plan is None:
            p = self.params
            n = max(1, math.ceil(dt / p.substep - 1e-9))
            h = dt / n
            plan = (n, h, math.exp(-h / p.motor_tau), math.radians(p.steer_rate_deg_s) * h)
            if len(self._cache) < 64:
                self._cache[dt] = plan
        return plan

    def step(self, state: CarState, angle: float, throttle: float, dt: float) -> CarState:
        """The state after ``dt`` seconds of commands ``angle`` and ``throttle`` (each clipped to [-1, 1])."""
        if not dt > 0:
            if dt == 0:
                return state
            raise ValueError(f"BicycleModel.step: dt must be >= 0 seconds, got {dt!r}")
        p = self.params
        angle = clean_command(angle, "BicycleModel.step angle")
        throttle = clean_command(throttle, "BicycleModel.step throttle")
        n, h, decay, max_travel = self._plan(dt)
        target_steer = angle * p.max_steer
        target_speed = throttle * p.max_speed * (1.0 if throttle >= 0 else p.reverse_ratio)
        inv_wb = 1.0 / p.wheelbase
        x, y, th, v, st = state.x, state.y, state.heading, state.speed, state.steer
        for _ in range(n):
            d = target_steer - st
            st = target_steer if abs(d) <= max_travel else st + math.copysign(max_travel, d)
            v_new = target_speed + (v - target_speed) * decay
            # distance travelled under the exponential speed response, integrated exactly
            dist = target_speed * h + (v - target_speed) * p.motor_tau * (1.0 - decay)
            v = v_new
            # positive steer turns right, i.e. clockwise: heading decreases
            dth = -dist * math.tan(st) * inv_wb
            if abs(dth) < 1e-9:
                x += dist * math.cos(th + dth / 2)
                y += dist * math.sin(th + dth / 2)
            else:
                r = dist / dth
                x += r * (math.sin(th + dth) - math.sin(th))
                y -= r * (math.cos(th + dth) - math.cos(th))
            th += dth
        th = (th + math.pi) % (2 * math.pi) - math.pi
        return CarState(x, y, th, v, st)
