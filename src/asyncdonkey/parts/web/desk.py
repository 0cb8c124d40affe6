"""One driver at a time: who holds the controls, and what a drive command may contain.

With Donkeycar's web controller every open page sends its joystick, so two phones fight over the car and the
one whose stick is at rest keeps sending zeros. Here the car has one *driver* at a time; every other page
watches (video, mode, record count, health) and its drive commands are ignored. The rules:

* **Taking control**: a client's drive command takes control when nobody holds it, or when the holder has sent
  nothing for ``idle_release_s`` (it went quiet: a frozen page, a dead link).
* **Keeping it**: the driver's page sends its command at a steady rate while it drives, so it keeps control
  (and keeps its command fresh for the throttle's stale-command failsafe).
* **Releasing it**: the driver closes the page, its page goes hidden (it sends ``{"release": true}``), its
  connection drops, or it goes quiet for ``idle_release_s``.
* **Stop is for everyone**: ``{"stop": true}`` from any client stops the car (throttle 0, mode ``user``) and
  hands control to that client, so a watcher can always stop a car someone else drives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ..control import normalise_mode
from .auth import WebConfigError

__all__ = ["Command", "CommandError", "Desk", "parse_command"]


class CommandError(WebConfigError):
    """A drive command that cannot be used (the message names the key and what was expected)."""


@dataclass
class Command:
    """One parsed message: Donkeycar's keys (``None``: not given) and ours (``stop``, ``release``)."""

    angle: float | None = None
    throttle: float | None = None
    mode: str | None = None
    recording: bool | None = None
    buttons: dict[str, bool] | None = None
    stop: bool = False
    release: bool = False

    @property
    def drives(self) -> bool:
        """True when the message asks to drive (needs control); ``stop`` and ``release`` alone do not."""
        return (
            self.angle is not None
            or self.throttle is not None
            or self.mode is not None
            or self.recording is not None
            or bool(self.buttons)
        )


def _unit(data: dict[str, Any], key: str) -> float | None:
    v = data.get(key)
    if v is None:
        return None
    if isinstance(v, bool):
        raise CommandError(f"web command: {key!r} must be a number in [-1, 1], got {v!r}")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise CommandError(f"web command: {key!r} must be a number in [-1, 1], got {v!r}") from None
    if not math.isfinite(f):
        raise CommandError(f"web command: {key!r} must be a finite number, got {v!r}")
    return -1.0 if f < -1.0 else 1.0 if f > 1.0 else f


def parse_command(data: object) -> Command:
    """Validate a decoded JSON message (Donkeycar's ``angle, throttle, drive_mode, recording, buttons``).

    Numbers are clamped to [-1, 1]; a mode must be one of the drive modes (a typo must not hand the car to the
    pilot); ``recording`` must be a boolean; ``buttons`` a mapping of names to booleans.
    """
    if not isinstance(data, dict):
        raise CommandError(f"web command: expected a JSON object, got {type(data).__name__}")
    cmd = Command(angle=_unit(data, "angle"), throttle=_unit(data, "throttle"))
    if data.get("drive_mode") is not None:
        try:
            cmd.mode = normalise_mode(data["drive_mode"], "web command 'drive_mode'")
        except ValueError as exc:
            raise CommandError(str(exc)) from None
    rec = data.get("recording")
    if rec is not None:
        if not isinstance(rec, bool):
            raise CommandError(f"web command: 'recording' must be true or false, got {rec!r}")
        cmd.recording = rec
    buttons = data.get("buttons")
    if buttons is not None:
        if not isinstance(buttons, dict):
            raise CommandError(f"web command: 'buttons' must be an object of name: true/false, got {buttons!r}")
        cmd.buttons = {str(k): bool(v) for k, v in buttons.items()}
    cmd.stop = data.get("stop") is True
    cmd.release = data.get("release") is True
    return cmd


class Desk:
    """Who drives. Clients are identified by any hashable id (a WebSocket, ``"http:<peer>"`` for ``POST``).

    Args:
        idle_release_s: a driver that sends nothing for this long loses control to the next client that drives.
    """

    def __init__(self, idle_release_s: float = 1.0) -> None:
        if not (idle_release_s > 0 and math.isfinite(idle_release_s)):
            raise WebConfigError(f"WebController: idle_release_s must be a positive number, got {idle_release_s!r}")
        self.idle_release_s = float(idle_release_s)
        self.driver: object | None = None
        self.last_heard = -math.inf  # runtime-clock time of the driver's latest message
        self.refused = 0  # drive commands ignored because another client drives
        self.handovers = 0

    def is_free(self, now: float) -> bool:
        return self.driver is None or now - self.last_heard >= self.idle_release_s

    def claim(self, client: object, now: float, *, force: bool = False) -> bool:
        """Give ``client`` control if it holds it, nobody does, the holder went quiet, or ``force`` (stop)."""
        if client is not self.driver and client != self.driver:
            if not (force or self.is_free(now)):
                self.refused += 1
                return False
            self.driver = client
            self.handovers += 1
        self.last_heard = now
        return True

    def release(self, client: object) -> bool:
        """``client`` gives up control (if it held it). True when it did."""
        if self.driver is not None and (client is self.driver or client == self.driver):
            self.driver = None
            return True
        return False

    def expire(self, now: float) -> bool:
        """Release a driver that went quiet; true when one was released."""
        if self.driver is not None and now - self.last_heard >= self.idle_release_s:
            self.driver = None
            return True
        return False

    def role(self, client: object, now: float) -> str:
        """``"you"`` (``client`` drives), ``"other"`` (someone else does) or ``"free"``."""
        if self.driver is None or now - self.last_heard >= self.idle_release_s:
            return "free"
        return "you" if (client is self.driver or client == self.driver) else "other"
