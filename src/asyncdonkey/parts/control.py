"""Who drives: the user, the pilot, or both (Donkeycar's drive modes), and when to record.

Donkeycar's templates define these three small parts inline in every car script; here they are importable,
behave the same on the values Donkeycar gives them, and are strict where Donkeycar is silently lenient:

* a mode that is not one of the known names raises (Donkeycar drives on the pilot for any unknown string, so
  a typo in a controller mapping hands the car to the autopilot);
* ``None`` (nothing published yet) is the safe value everywhere: no mode yet means ``user``, no command yet
  means neutral.

Typical wiring (after the controller and the pilot, before the actuators)::

    v.add(PilotCondition(), inputs=["user/mode"], outputs=["run_pilot"])
    v.add(pilot, inputs=["cam/image_array"], outputs=["pilot/angle", "pilot/throttle"], run_condition="run_pilot")
    v.add(DriveMode(ai_throttle_mult=0.8),
          inputs=["user/mode", "user/angle", "user/throttle", "pilot/angle", "pilot/throttle"],
          outputs=["angle", "throttle"])
    v.add(AutoRecordOnThrottle(), inputs=["user/mode", "user/throttle"], outputs=["recording"])
"""

from __future__ import annotations

import math
import time
from typing import Final

from ..clock import get_clock

__all__ = [
    "DRIVE_MODES",
    "LOCAL",
    "LOCAL_ANGLE",
    "USER",
    "AutoRecordOnThrottle",
    "DriveMode",
    "PilotCondition",
    "normalise_mode",
]

USER: Final = "user"
LOCAL_ANGLE: Final = "local_angle"
LOCAL: Final = "local"
#: The modes in the order a controller's mode button cycles through them.
DRIVE_MODES: Final = (USER, LOCAL_ANGLE, LOCAL)
#: Other spellings of the same modes found in Donkeycar's code and docs.
_ALIASES: Final = {"local_pilot": LOCAL, "pilot": LOCAL}


def normalise_mode(mode: object, where: str = "drive mode") -> str:
    """Return the canonical mode name for ``mode``; ``None`` (no controller output yet) is ``user``.

    Raises ``ValueError`` naming ``where`` for anything else, so a misspelt mode fails loudly instead of
    handing the car to the pilot.
    """
    if mode is None:
        return USER
    if isinstance(mode, str):
        if mode in DRIVE_MODES:
            return mode
        alias = _ALIASES.get(mode)
        if alias is not None:
            return alias
    raise ValueError(f"{where}: unknown mode {mode!r}; expected one of {', '.join(DRIVE_MODES)} (or None)")


def _now() -> float:
    """Runtime time on the running loop (virtual under the virtual clock), monotonic time outside one."""
    try:
        return get_clock().now()
    except RuntimeError:
        return time.monotonic()


def _command(value: object) -> float:
    """A steering/throttle command: ``None`` or NaN is neutral (0.0), anything else a float."""
    if value is None:
        return 0.0
    f = float(value)  # type: ignore[arg-type]
    return 0.0 if math.isnan(f) else f


class PilotCondition:
    """``run_pilot`` is true when the pilot has a say (any mode but ``user``).

    Use its output as the pilot's ``run_condition`` so no inference runs while the user drives.
    """

    def run(self, mode: object) -> bool:
        return normalise_mode(mode, "PilotCondition") != USER


#: ``DriveMode.output_sources``: for each mode, the index of the input (mode, user angle, user throttle, pilot
#: angle, pilot throttle) each output (angle, throttle) is passed on from
_SOURCES: Final = {USER: (1, 2), LOCAL_ANGLE: (3, 2), LOCAL: (3, 4)}


class DriveMode:
    """Choose the command the actuators get, from the mode.

    * ``user``: user angle, user throttle;
    * ``local_angle``: pilot angle, user throttle;
    * ``local``: pilot angle, pilot throttle times ``ai_throttle_mult``.

    A pilot value that is ``None`` (the pilot has not produced one yet) or NaN is 0.0, as in Donkeycar; a user
    value that is ``None`` passes through as ``None``, which the actuators treat as neutral. It declares which
    input each output came from (:meth:`output_sources`), so each command is as old as the input it was chosen
    from (``docs/provenance.md``).
    """

    def __init__(self, ai_throttle_mult: float = 1.0) -> None:
        mult = float(ai_throttle_mult)
        if not math.isfinite(mult) or mult < 0:
            raise ValueError(f"DriveMode: ai_throttle_mult must be a finite number >= 0, got {ai_throttle_mult!r}")
        self.ai_throttle_mult = mult

    def run(
        self,
        mode: object,
        user_angle: float | None,
        user_throttle: float | None,
        pilot_angle: float | None,
        pilot_throttle: float | None,
    ) -> tuple[float | None, float | None]:
        m = normalise_mode(mode, "DriveMode")
        if m == USER:
            return user_angle, user_throttle
        if m == LOCAL_ANGLE:
            return _command(pilot_angle), user_throttle
        return _command(pilot_angle), _command(pilot_throttle) * self.ai_throttle_mult

    def output_sources(self, mode: object, *_: object) -> tuple[int, int]:
        """Which input each output came from (``asyncdonkey.core.origin_sources``): the driver's command is dated by the
        driver's input, the pilot's by the pilot's, so a stale pilot does not cut a driver in ``user`` mode and a
        fresh gamepad does not hide a silent pilot in ``local`` mode. A ``0.0`` put in for a pilot value that is
        missing is dated by that pilot input (none if it was never written: no age to drive on)."""
        return _SOURCES.get(mode) or _SOURCES[normalise_mode(mode, "DriveMode")]  # (run() has checked the mode)


class AutoRecordOnThrottle:
    """Record while the user is driving with the throttle open (Donkeycar's ``AUTO_RECORD_ON_THROTTLE``).

    ``recording`` is true when ``|throttle| > dead_zone`` in ``user`` mode. Frames where the car stands still
    or the pilot drives teach a pilot nothing it should copy, so they are not recorded. With ``hold_s`` the
    recording continues that long (runtime clock, so virtual under the virtual clock) after the throttle
    closes: a driver lifting off for a bend would otherwise cut the bend out of the data. Leaving ``user``
    mode stops recording at once.
    """

    def __init__(self, dead_zone: float = 0.0, *, hold_s: float = 0.0) -> None:
        if not (dead_zone >= 0 and hold_s >= 0):
            raise ValueError(f"AutoRecordOnThrottle: dead_zone and hold_s must be >= 0, got {dead_zone!r}, {hold_s!r}")
        self.dead_zone = float(dead_zone)
        self.hold_s = float(hold_s)
        self._last_open: float | None = None  # runtime time the throttle was last seen open

    def run(self, mode: object, throttle: float | None) -> bool:
        if normalise_mode(mode, "AutoRecordOnThrottle") != USER:
            self._last_open = None
            return False
        if self.hold_s <= 0:
            return abs(_command(throttle)) > self.dead_zone
        now = _now()
        if abs(_command(throttle)) > self.dead_zone:
            self._last_open = now
            return True
        return self._last_open is not None and now - self._last_open <= self.hold_s
