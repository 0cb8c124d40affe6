"""Joystick controller part: Donkeycar's ``user/angle, user/throttle, user/mode, recording`` from a gamepad.

The device is read by :class:`~asyncdonkey.hw.joystick.JoystickReader` on the event loop (no thread, no
blocking read). Axes are level-triggered (the tick reads their current value); buttons are edge-triggered and
handled *as the events arrive*, so a press-and-release shorter than a tick still cycles the mode or toggles
recording exactly once.

Mapping (:class:`JoystickMapping`, defaults for an Xbox-style pad under Linux's ``xpad`` driver, also the
layout of a Logitech F710 in X mode and most PS4/PS5 pads under ``hid-sony`` for the sticks):

==========================  ======================================  =========================================
what                        default                                 how
==========================  ======================================  =========================================
steering                    axis 0 (left stick, horizontal)         value/32767, deadzone, x ``steering_scale``
throttle                    axis 4 (right stick, vertical),         inverted (stick up is negative on Linux),
                            inverted                                deadzone, x ``throttle_scale`` x max
mode cycle                  button 0 (A / cross)                    user → local_angle → local → user
recording toggle            button 1 (B / circle)                   on ↔ off
emergency stop              button 3 (Y / triangle)                 throttle 0 and mode ``user`` at once
==========================  ======================================  =========================================

Deadzone: a stick within ``deadzone`` of centre reads 0; beyond it the range is stretched so output is
continuous (at the deadzone edge 0, at full deflection ±1).

Emergency stop: pressing the button forces throttle 0 and mode ``user`` (the pilot loses control at once).
The stop holds until the button is released *and* the throttle stick has come back to neutral, so letting go
of the button with the stick still pushed does not lurch the car.

Unplug: outputs go neutral (angle 0, throttle 0), the mode returns to ``user`` and recording stops; the reader
keeps trying to reopen the device. After a replug the sticks count from their reported initial state.

Outputs: ``run()`` (and ``run_threaded()``, identical) return ``(angle, throttle, mode, recording)``. Add it as
``v.add(ctr, outputs=ctr.outputs)`` or with ``threaded=True``; its ``async update()`` keeps the device read.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from ..clock import get_clock
from ..hw.joystick import JoystickEvent, JoystickReader
from .control import DRIVE_MODES

__all__ = ["CONTROLLER_OUTPUTS", "DRIVE_MODES", "JoystickController", "JoystickMapping"]

logger = logging.getLogger(__name__)

CONTROLLER_OUTPUTS = ("user/angle", "user/throttle", "user/mode", "recording")


@dataclass(frozen=True)
class JoystickMapping:
    """Which axes and buttons do what (see the module docstring for the defaults)."""

    steering_axis: int = 0
    throttle_axis: int = 4
    invert_steering: bool = False
    invert_throttle: bool = True
    steering_scale: float = 1.0
    throttle_scale: float = 1.0
    deadzone: float = 0.05
    mode_button: int | None = 0
    record_button: int | None = 1
    estop_button: int | None = 3
    modes: tuple[str, ...] = field(default=DRIVE_MODES)

    def __post_init__(self) -> None:
        if not 0.0 <= self.deadzone < 1.0:
            raise ValueError(f"JoystickMapping: deadzone must be in [0, 1), got {self.deadzone!r}")
        if not self.modes:
            raise ValueError("JoystickMapping: modes must list at least one drive mode")
        buttons = [b for b in (self.mode_button, self.record_button, self.estop_button) if b is not None]
        if len(set(buttons)) != len(buttons):
            raise ValueError(f"JoystickMapping: mode, record and e-stop buttons must differ, got {buttons}")


def shape_axis(raw: float, deadzone: float, invert: bool, scale: float) -> float:
    """Scaled axis value in [-1, 1] → deadzone applied and stretched, inverted, scaled."""
    v = -1.0 if raw < -1.0 else 1.0 if raw > 1.0 else raw
    mag = abs(v)
    if mag <= deadzone:
        return 0.0
    out = (mag - deadzone) / (1.0 - deadzone)
    out = out if v > 0 else -out
    if invert:
        out = -out
    return out * scale


class JoystickController:
    """A Linux gamepad as a Donkeycar controller part.

    Args:
        device: the joystick device (Donkeycar's ``JOYSTICK_DEVICE_FILE``, default ``/dev/input/js0``).
        mapping: axes and buttons (:class:`JoystickMapping`).
        max_throttle: throttle output is multiplied by this (``JOYSTICK_MAX_THROTTLE``, default 1.0).
        steering_scale: overrides ``mapping.steering_scale`` (``JOYSTICK_STEERING_SCALE``).
        reconnect_s: seconds between attempts to reopen a missing device.
        reader: a ready :class:`JoystickReader` (tests, or sharing one device).
    """

    def __init__(
        self,
        device: str = "/dev/input/js0",
        mapping: JoystickMapping | None = None,
        *,
        max_throttle: float = 1.0,
        steering_scale: float | None = None,
        reconnect_s: float = 1.0,
        reader: JoystickReader | None = None,
    ) -> None:
        if not (isinstance(max_throttle, int | float) and 0.0 <= max_throttle <= 1.0):
            raise ValueError(f"JoystickController({device}): max_throttle must be in [0, 1], got {max_throttle!r}")
        m = mapping or JoystickMapping()
        if steering_scale is not None:
            m = JoystickMapping(**{**m.__dict__, "steering_scale": float(steering_scale)})
        self.mapping = m
        self.outputs: list[str] = list(CONTROLLER_OUTPUTS)
        self.max_throttle = float(max_throttle)
        self.reader = reader or JoystickReader(device, reconnect_s=reconnect_s)
        self.reader.on_event = self._on_event
        self.reader.on_disconnect = self._on_disconnect
        self.mode = m.modes[0]
        self.recording = False
        self.estop = False
        self.estop_events = 0
        self._lost_at: float | None = None

    @property
    def connected(self) -> bool:
        return self.reader.connected

    # ------------------------------------------------------------------------------------------ events
    def _on_event(self, ev: JoystickEvent) -> None:
        m = self.mapping
        if ev.is_button:
            if ev.init:
                return  # initial state, not a press
            pressed = bool(ev.value)
            if ev.number == m.estop_button:
                if pressed:
                    self.emergency_stop()
                else:
                    self._maybe_release_estop()
            elif not pressed:
                return
            elif ev.number == m.mode_button and not self.estop:
                i = m.modes.index(self.mode) if self.mode in m.modes else -1
                self.mode = m.modes[(i + 1) % len(m.modes)]
                logger.info("joystick %s: mode %s", self.reader.device, self.mode)
            elif ev.number == m.record_button:
                self.recording = not self.recording
                logger.info("joystick %s: recording %s", self.reader.device, "on" if self.recording else "off")
        elif ev.is_axis and ev.number == m.throttle_axis and self.estop:
            self._maybe_release_estop()

    def emergency_stop(self) -> None:
        """Throttle 0 and mode ``user`` until the e-stop button is up and the throttle stick is neutral."""
        if not self.estop:
            self.estop_events += 1
            logger.warning("joystick %s: emergency stop", self.reader.device)
        self.estop = True
        self.mode = self.mapping.modes[0]

    def _maybe_release_estop(self) -> None:
        m = self.mapping
        if m.estop_button is not None and self.reader.state.button(m.estop_button):
            return
        if self._throttle_from_stick() == 0.0:
            self.estop = False

    def _on_disconnect(self) -> None:
        self.mode = self.mapping.modes[0]
        self.recording = False
        if self._lost_at is None:
            self._lost_at = get_clock().now()

    def output_origin(self) -> float | None:
        """While the device is connected the stick state is current (a held stick sends no events, yet the
        driver's command is fresh): ``None``, i.e. now. Once unplugged, the time it was lost, so the commands
        age and a stale-command failsafe stops the car."""
        if self.reader.connected:
            self._lost_at = None
            return None
        return self._lost_at

    # ------------------------------------------------------------------------------------------ outputs
    def _throttle_from_stick(self) -> float:
        m = self.mapping
        return shape_axis(self.reader.state.axis(m.throttle_axis), m.deadzone, m.invert_throttle, m.throttle_scale)

    def run(self) -> tuple[float, float, str, bool]:
        """``(user/angle, user/throttle, user/mode, recording)`` from the current stick and button state."""
        m = self.mapping
        state = self.reader.state
        angle = shape_axis(state.axis(m.steering_axis), m.deadzone, m.invert_steering, m.steering_scale)
        throttle = 0.0 if self.estop else self._throttle_from_stick() * self.max_throttle
        return angle, throttle, self.mode, self.recording

    run_threaded = run

    async def update(self) -> None:
        """Keep the device read (reconnecting) until :meth:`shutdown`; runs as a task beside the ticks."""
        await self.reader.run()

    def shutdown(self) -> Any:
        self.reader.close()
