"""``Controls``: what the web controller outputs each tick, and the car state its pages show.

Kept apart from the server so the part's whole output (angle, throttle, mode, recording, buttons) and the rules
that change it are in one small object: a command from a page sets it (:meth:`Controls.drive`), a stop or a
release puts it in neutral, and each tick merges the car's own state in (:meth:`Controls.tick`), reporting what
changed so the pages can be told.
"""

from __future__ import annotations

from typing import Any

from ..control import USER, normalise_mode
from .intake import Command

__all__ = ["Controls"]


class Controls:
    """The controller's outputs and the car state shown on the pages.

    A mode or recording chosen on a page is *latched*: it is the output of the next tick even if the car's own
    ``user/mode``/``recording`` input (one tick old) still says otherwise, as in Donkeycar.
    """

    __slots__ = (
        "angle",
        "buttons",
        "commands",
        "mode",
        "mode_latch",
        "num_records",
        "origin",
        "recording",
        "recording_latch",
        "throttle",
        "ticks",
    )

    def __init__(self, mode: str) -> None:
        self.angle = 0.0
        self.throttle = 0.0
        self.mode = mode
        self.recording = False
        self.num_records = 0
        self.mode_latch: str | None = None
        self.recording_latch: bool | None = None
        self.buttons: dict[str, bool] = {}
        #: arrival time of the driver's latest command (runtime clock), what ``throttle@age`` measures
        self.origin: float | None = None
        self.commands = 0  # drive commands applied
        self.ticks = 0

    def tick(self, mode: Any, recording: Any, num_records: Any) -> tuple[dict[str, Any], dict[str, bool]]:
        """Merge one tick's inputs; returns the changes to push to the pages and this tick's buttons."""
        self.ticks += 1
        changes: dict[str, Any] = {}
        if mode is not None:
            m = normalise_mode(mode, "WebController input 'user/mode'")
            if m != self.mode:
                self.mode = m
                changes["driveMode"] = m
        if self.mode_latch is not None:
            self.mode, self.mode_latch = self.mode_latch, None
            changes["driveMode"] = self.mode
        if recording is not None and bool(recording) != self.recording:
            self.recording = bool(recording)
            changes["recording"] = self.recording
        if self.recording_latch is not None:
            self.recording, self.recording_latch = self.recording_latch, None
            changes["recording"] = self.recording
        if num_records is not None and num_records != self.num_records:
            before, self.num_records = self.num_records, int(num_records)
            # every tenth record, as Donkeycar pushes it; a count that jumps past a multiple of ten (the writer
            # counts records once they are on disk, two at a time now and then) still crosses it
            if self.recording and self.num_records // 10 != before // 10:
                changes["num_records"] = self.num_records
        # Donkeycar's button latch: a press is reported on one tick, then as released on the next
        buttons = self.buttons
        self.buttons = {name: False for name, pressed in buttons.items() if pressed}
        return changes, buttons

    def outputs(self, buttons: dict[str, bool]) -> tuple[float, float, str, bool, dict[str, bool]]:
        """The part's outputs: ``angle, throttle, mode, recording, buttons``."""
        return self.angle, self.throttle, self.mode, self.recording, buttons

    def stop(self, now: float) -> None:
        """Stop: throttle 0 and the mode back to ``user`` (the pilot loses the car too), as a fresh command."""
        self.throttle = 0.0
        self.mode_latch = USER
        self.origin = now

    def neutral(self) -> None:
        """The driver let go: a neutral command, keeping the *old* arrival time so the failsafe sees its age."""
        self.throttle = 0.0
        self.angle = 0.0

    def drive(self, cmd: Command, max_throttle: float, now: float) -> None:
        """Apply the values of a drive command from the client holding control."""
        if cmd.angle is not None:
            self.angle = cmd.angle
        if cmd.throttle is not None:
            self.throttle = 0.0 if cmd.stop else cmd.throttle * max_throttle
        if cmd.mode is not None and not cmd.stop:
            self.mode = self.mode_latch = cmd.mode
        if cmd.recording is not None:
            self.recording = self.recording_latch = cmd.recording
        if cmd.buttons:
            for name, pressed in cmd.buttons.items():
                if pressed:
                    self.buttons[name] = True
        self.origin = now
        self.commands += 1
