"""Live PWM calibration from the web page (Donkeycar's ``/calibrate``), on our steering and throttle parts.

Donkeycar's ``/wsCalibrate`` takes ``{"config": {"STEERING_LEFT_PWM": 460, ...}}`` and sets the pulses on the
drive train while the car runs, so the owner can find the end points with the wheels in the air. The same keys
set :class:`~asyncdonkey.parts.actuators.PWMSteering` (``left_pulse``, ``right_pulse``) and
:class:`~asyncdonkey.parts.actuators.PWMThrottle` (``max_pulse``, ``zero_pulse``, ``min_pulse``). Values are
checked first (whole numbers in the PCA9685's 0..4095, end points apart from centre and stop), so a slip of
the finger cannot leave the steering with no range; the neutral pulses (steering centre, throttle stopped)
follow, since the actuators fall back to them at shutdown and in the failsafe.
"""

from __future__ import annotations

from typing import Any

from .auth import WebConfigError

__all__ = ["STEERING_KEYS", "THROTTLE_KEYS", "CalibrationError", "apply_calibration", "current_calibration"]

STEERING_KEYS = {"STEERING_LEFT_PWM": "left_pulse", "STEERING_RIGHT_PWM": "right_pulse"}
THROTTLE_KEYS = {
    "THROTTLE_FORWARD_PWM": "max_pulse",
    "THROTTLE_STOPPED_PWM": "zero_pulse",
    "THROTTLE_REVERSE_PWM": "min_pulse",
}


class CalibrationError(WebConfigError):
    """A calibration request that cannot be applied (the message names the setting)."""


def current_calibration(steering: Any, throttle: Any) -> dict[str, int]:
    """The calibration of the parts given (``None``: that part is not calibrated from the web)."""
    out: dict[str, int] = {}
    for part, keys in ((steering, STEERING_KEYS), (throttle, THROTTLE_KEYS)):
        if part is not None:
            out.update({key: int(getattr(part, attr)) for key, attr in keys.items()})
    return out


def _pulse(key: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value):
        raise CalibrationError(f"calibration: {key} must be a whole number of pulse units, got {value!r}")
    v = int(value)
    if not 0 <= v <= 4095:
        raise CalibrationError(f"calibration: {key} must be in 0..4095 (PCA9685 pulse units), got {v}")
    return v


def apply_calibration(steering: Any, throttle: Any, config: object) -> dict[str, int]:
    """Check every value of ``config`` first, then set them all; returns the calibration now in force."""
    if not isinstance(config, dict):
        raise CalibrationError(f"calibration: 'config' must be an object of setting: value, got {config!r}")
    known = {**STEERING_KEYS, **THROTTLE_KEYS}
    steer_new: dict[str, int] = {}
    throttle_new: dict[str, int] = {}
    for key, value in config.items():
        if key not in known:
            raise CalibrationError(f"calibration: unknown setting {key!r}; expected one of {', '.join(known)}")
        part, target = (steering, steer_new) if key in STEERING_KEYS else (throttle, throttle_new)
        if part is None:
            which = "steering" if key in STEERING_KEYS else "throttle"
            raise CalibrationError(f"calibration: {key} needs the {which} part (WebController({which}=...))")
        target[known[key]] = _pulse(key, value)
    try:  # both parts checked before either changes
        if steer_new:
            steering.calibrate(**steer_new, check_only=True)
        if throttle_new:
            throttle.calibrate(**throttle_new, check_only=True)
    except ValueError as exc:
        raise CalibrationError(f"calibration: {exc}") from None
    if steer_new:
        steering.calibrate(**steer_new)
    if throttle_new:
        throttle.calibrate(**throttle_new)
    return current_calibration(steering, throttle)
