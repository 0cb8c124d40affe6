"""Live PWM calibration from the web page (Donkeycar's ``/calibrate``), on our steering and throttle parts.

Donkeycar's ``/wsCalibrate`` takes ``{"config": {"STEERING_LEFT_PWM": 460, ...}}`` and sets the pulses on the
drive train while the car runs, so the owner can find the end points with the wheels in the air. The same keys
set :class:`~asyncdonkey.parts.actuators.PWMSteering` (``left_pulse``, ``right_pulse``) and
:class:`~asyncdonkey.parts.actuators.PWMThrottle` (``max_pulse``, ``zero_pulse``, ``min_pulse``).

A calibration changes what the car does with every command, so it is guarded as a command and more:

* each value goes through the web boundary's gate (:func:`admit_config`: a finite whole number in the
  PCA9685's 0..4095; ``NaN``, ``inf``, a 400-digit integer, ``"480"`` are refused and counted);
* the calibration that would result is checked before anything is set (left ≠ right, and the stopped pulse
  strictly between the reverse and forward pulses: a "stopped" pulse past forward is full throttle);
* the stopped pulse never changes during a drive: it is the one the ESC was armed with and the one every safe
  path writes (the throttle's ``safe_pulse``; the part itself refuses, :class:`~..actuators.CalibrationLocked`,
  counted here as ``armed``). The end points and the steering pulses may change;
* only while the car is disarmed (:func:`why_not_stopped`) and only by the driver (the controller asks its
  desk, :meth:`~.desk.Desk.why_not_calibrator`), every request logged with who made it;
* read back: the calibration in force afterwards must be what was asked (:func:`apply_calibration`).

The steering centre a zero command maps to follows a steering calibration, but what the car falls back to
(shutdown, the watchdog, the safety process) stays the centre the drive started with: a value typed into a
page never redefines "safe" during a drive.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from typing import Any

from ...contracts import Contract
from ...ratelimit import LogThrottle
from ..actuators import CalibrationLocked
from ..control import USER
from .auth import WebConfigError
from .intake import Intake

__all__ = [
    "CALIBRATION",
    "STEERING_KEYS",
    "THROTTLE_KEYS",
    "CalibrationError",
    "CalibrationRecords",
    "admit_config",
    "apply_calibration",
    "current_calibration",
    "why_not_stopped",
]

STEERING_KEYS = {"STEERING_LEFT_PWM": "left_pulse", "STEERING_RIGHT_PWM": "right_pulse"}
THROTTLE_KEYS = {
    "THROTTLE_FORWARD_PWM": "max_pulse",
    "THROTTLE_STOPPED_PWM": "zero_pulse",
    "THROTTLE_REVERSE_PWM": "min_pulse",
}
logger = logging.getLogger("asyncdonkey.parts.web.controller")  # the controller's log, where owners look

#: the channel a calibration message's refusals are counted under (not an object, unknown setting, ...)
CALIBRATION = "web/calibration"


class CalibrationError(WebConfigError):
    """A calibration request that cannot be applied (the message names the setting).

    ``channel`` and ``reason`` are what the web gate counts it under; ``in_force`` is the calibration in force
    when the error is about what was set (a read-back that differs)."""

    def __init__(
        self,
        message: str,
        in_force: dict[str, int] | None = None,
        *,
        channel: str = CALIBRATION,
        reason: str = "calibration",
    ) -> None:
        super().__init__(message)
        self.in_force = in_force
        self.channel = channel
        self.reason = reason


def current_calibration(steering: Any, throttle: Any) -> dict[str, int]:
    """The calibration of the parts given (``None``: that part is not calibrated from the web)."""
    out: dict[str, int] = {}
    for part, keys in ((steering, STEERING_KEYS), (throttle, THROTTLE_KEYS)):
        if part is not None:
            out.update({key: int(getattr(part, attr)) for key, attr in keys.items()})
    return out


def admit_config(intake: Intake, config: object) -> dict[str, int]:
    """A calibration message's ``config``, each value through the web gate (channel ``calibration/<KEY>``).

    Raises :class:`CalibrationError` naming every refused value (each counted at the gate)."""
    if not isinstance(config, dict):
        what = f"'config' must be an object of setting: value, got {config!r:.40}"
        raise CalibrationError(str(intake.refuse(CALIBRATION, "type", what)))
    known = {**STEERING_KEYS, **THROTTLE_KEYS}
    out: dict[str, int] = {}
    errors: list[str] = []
    for key, value in config.items():
        try:
            if key not in known:
                what = f"unknown setting {key!r:.40} (expected one of {', '.join(known)})"
                raise intake.refuse(CALIBRATION, "unknown", what)
            out[key] = _pulse(intake, key, value)
        except WebConfigError as exc:
            errors.append(str(exc))
    if errors:
        raise CalibrationError("; ".join(errors))
    return out


_PULSE = Contract.number(0, 4095)


def _pulse(intake: Intake, key: str, value: object) -> int:
    """One pulse: a finite number in 0..4095 (the gate's contract), and whole (PCA9685 ticks)."""
    pulse = intake.admit(f"calibration/{key}", value, key, _PULSE)
    if pulse != int(pulse):
        raise intake.refuse(f"calibration/{key}", "fraction", f"{key!r}: {pulse} is not a whole number of pulse units")
    return int(pulse)


def why_not_stopped(command: float, mode: str, throttle: Any) -> str | None:
    """Why the car is not disarmed (``None``: it is). Disarmed is all of: the controller's throttle command is 0;
    the throttle's target and its last write are both its safe pulse (the stopped pulse the drive armed the ESC
    with: nothing else drives it, a write that failed or is still on its way counts as moving); and the drive
    mode is ``user``, so no pilot can take the throttle at the next tick."""
    if command != 0.0:
        return f"the throttle command is {command:+.2f}"
    if throttle is not None:
        stopped = int(getattr(throttle, "safe_pulse", throttle.neutral_pulse))
        out = getattr(throttle, "written_pulse", None)
        if out != stopped or getattr(throttle, "pulse", out) != stopped:
            return f"the throttle's output is at pulse {out}, not at the stopped pulse {stopped}"
    if mode != USER:
        return f"a pilot may be driving (mode {mode!r})"
    return None


def _check_stopped_between(throttle: Any, new: dict[str, int]) -> None:
    """The stopped pulse must lie strictly between reverse and forward (either way round: an ESC may be
    wired reversed): a "stopped" pulse at or past an end point is full throttle."""
    vals = {attr: new.get(attr, getattr(throttle, attr)) for attr in THROTTLE_KEYS.values()}
    lo, hi = sorted((vals["min_pulse"], vals["max_pulse"]))
    if not lo < vals["zero_pulse"] < hi:
        raise CalibrationError(
            f"calibration: THROTTLE_STOPPED_PWM ({vals['zero_pulse']}) must be strictly between "
            f"THROTTLE_REVERSE_PWM ({vals['min_pulse']}) and THROTTLE_FORWARD_PWM ({vals['max_pulse']})",
            channel="calibration/THROTTLE_STOPPED_PWM",
            reason="range",
        )


def apply_calibration(steering: Any, throttle: Any, config: object) -> dict[str, int]:
    """Check every value of ``config`` first, then set them all, then read back; returns the calibration in force.

    Raises :class:`CalibrationError` when a value or the resulting calibration is refused (nothing set), or when
    the calibration read back differs from what was asked (``in_force`` says what is)."""
    if not isinstance(config, dict):
        raise CalibrationError(f"calibration: 'config' must be an object of setting: value, got {config!r:.40}")
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
        target[known[key]] = _whole_pulse(key, value)
    locked: CalibrationLocked | None = None
    try:  # both parts checked before either changes
        if steer_new:
            steering.calibrate(**steer_new, check_only=True)
        if throttle_new:
            try:
                throttle.calibrate(**throttle_new, check_only=True)
            except CalibrationLocked as exc:
                locked = exc  # said after the value checks: a stopped pulse past forward is told so first
    except ValueError as exc:
        raise CalibrationError(f"calibration: {exc}") from None
    if throttle_new:
        _check_stopped_between(throttle, throttle_new)
    if locked is not None:
        raise CalibrationError(f"calibration: {locked}", channel="calibration/THROTTLE_STOPPED_PWM", reason="armed")
    if steer_new:
        steering.calibrate(**steer_new)
    if throttle_new:
        throttle.calibrate(**throttle_new)
    return _read_back(steering, throttle, {k: int(v) for k, v in config.items()})


def _whole_pulse(key: str, value: object) -> int:
    """The pulse check for callers without a gate: a finite whole number in 0..4095 (never raises anything
    but :class:`CalibrationError`: ``int(inf)`` would be an ``OverflowError``)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CalibrationError(f"calibration: {key} must be a whole number of pulse units, got {value!r:.40}")
    if isinstance(value, float) and not (math.isfinite(value) and value == int(value)):
        raise CalibrationError(f"calibration: {key} must be a whole number of pulse units, got {value!r}")
    if not 0 <= value <= 4095:
        raise CalibrationError(f"calibration: {key} must be in 0..4095 (PCA9685 pulse units), got {value!r:.40}")
    return int(value)


def _read_back(steering: Any, throttle: Any, asked: dict[str, int]) -> dict[str, int]:
    """The calibration in force, checked against what was asked, the stopped pulse and the centre included
    (what a zero command maps to): a part that took a value and kept another is an error, not a success."""
    in_force = current_calibration(steering, throttle)
    wrong = {k: (v, in_force.get(k)) for k, v in asked.items() if in_force.get(k) != v}
    if "THROTTLE_STOPPED_PWM" in asked and int(throttle.neutral_pulse) != asked["THROTTLE_STOPPED_PWM"]:
        wrong["the throttle's stopped pulse"] = (asked["THROTTLE_STOPPED_PWM"], int(throttle.neutral_pulse))
    if wrong:
        said = ", ".join(f"{k} asked {a}, in force {b}" for k, (a, b) in wrong.items())
        raise CalibrationError(f"calibration: the read-back differs: {said}", in_force, reason="readback")
    return in_force


class CalibrationRecords:
    """The latest calibration requests, accepted or refused, each with when, who, what was asked, what changed
    and why not; every one logged (refusals rate-limited per client: one a second, so a page retrying in a loop
    cannot flood the log).

    Args:
        keep: how many of the latest requests are kept (:attr:`records`).
    """

    __slots__ = ("_log", "records")

    def __init__(self, keep: int = 100) -> None:
        self.records: deque[dict[str, Any]] = deque(maxlen=keep)
        self._log = LogThrottle(1.0)

    def accepted(self, now: float, who: str, asked: dict[str, int], changed: dict[str, list[int]]) -> None:
        """Keep and log an applied calibration: ``changed`` maps each setting to ``[before, after]``."""
        self.records.append({"t": now, "who": who, "asked": asked, "changed": changed, "refused": None})
        said = ", ".join(f"{k} {a} -> {b}" for k, (a, b) in changed.items()) or "nothing changed"
        logger.info("web: calibration by %s: %s", who, said)

    def refused(self, now: float, who: str, asked: object, exc: CalibrationError) -> None:
        """Keep and log a refused calibration with who asked."""
        record = asked if isinstance(asked, dict) else repr(asked)[:80]
        self.records.append({"t": now, "who": who, "asked": record, "changed": {}, "refused": str(exc)})
        more = self._log.ready(who, now, "refusals")
        if more is not None:
            logger.warning("web: calibration refused for %s (asked %.200s): %s%s", who, record, exc, more)
