"""What a web client sends, admitted value by value through the car's contracts before anything is applied.

Why. A browser page sends numbers in [-1, 1], but anyone with the token can send anything: ``NaN`` (Python's
``json`` reads it), ``1e999`` (read as ``inf``), a 400-digit integer (too large for a float: ``OverflowError``),
``"0.5"``, ``[0.5]``, ``true``, a mode the car does not have, an empty body, text that is not JSON or a JSON
array nested a thousand deep (``RecursionError``), or a megabyte. None of these is a command; each one used to
be a 500 or a dropped driver's connection, and a clamped ``1e300`` would have been full throttle.

Here each message is decoded within a size limit, and each value it carries goes through the web boundary's
:class:`~asyncdonkey.contracts.Gate` (the car's contracts: ``user/angle``, ``user/throttle`` are numbers in
[-1, 1], ``user/mode`` one of the drive modes, ``recording`` a bool). A message with any refused value is
refused whole: nothing of it is applied, so the last good command stays and ages, and the throttle's
stale-command failsafe decides what the car does, never the bad value. Refusals are counted per channel and
reason by the gate (``gate.counts()``) and logged rate-limited; the client is told why (``CommandError``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

from ...contracts import Contract, Contracts, ContractViolation, Gate, default_contracts
from ..control import DRIVE_MODES, normalise_mode
from .auth import WebConfigError

__all__ = [
    "COMMAND",
    "MAX_MESSAGE_BYTES",
    "Command",
    "CommandError",
    "Intake",
    "parse_command",
]

#: the largest message taken (a WebSocket text or a ``POST`` body): a drive command is under 200 bytes
MAX_MESSAGE_BYTES: Final = 8 * 1024
#: the channel a whole message's refusals are counted under (empty, not JSON, too large, not an object)
COMMAND: Final = "web/command"
#: the channel a button mapping's refusals are counted under (Donkeycar's ``web/buttons`` output)
BUTTONS: Final = "web/buttons"
_MAX_BUTTONS = 32
_MAX_BUTTON_NAME = 64

#: message key → (the channel whose contract it must meet, what the message calls it)
_VALUES: Final = {
    "angle": "user/angle",
    "throttle": "user/throttle",
    "drive_mode": "user/mode",
    "recording": "recording",
}
#: the flags of our own messages, true or false
_FLAGS: Final = {"stop": "web/stop", "release": "web/release"}
_FLAG = Contract.boolean()
#: the contracts the web boundary falls back to when the car has none for a channel: never nothing
_FALLBACK: Final = default_contracts()


class CommandError(WebConfigError):
    """A message or value that cannot be used (the message names the key and what was expected)."""


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


class Intake:
    """The web boundary: messages decoded within limits, values admitted through one :class:`Gate`.

    Args:
        gate: the boundary's gate (``contracts.gate("web")``); its counters are what ``/status`` shows.
        modes: the drive modes this controller offers (a mode the contract allows but the car does not offer is
            refused too: a car without a pilot must not be handed to one).
        now: the runtime clock, for the gate's rate-limited log.
    """

    def __init__(self, gate: Gate, modes: Sequence[str], now: Callable[[], float]) -> None:
        self.gate = gate
        self.modes = tuple(modes)
        self._now = now

    # ------------------------------------------------------------------------------------------ refusals
    def refuse(self, channel: str, reason: str, detail: str) -> CommandError:
        """Count and log one refusal at the gate; returns the error to raise (its text is what the client sees)."""
        try:
            now = self._now()
        except RuntimeError:  # called outside the drive's loop (a script, a test): only the log's rate uses it
            now = time.monotonic()
        self.gate.refuse(channel, reason, detail, now)
        return CommandError(detail)

    def admit(self, channel: str, value: Any, key: str, contract: Contract | None = None) -> Any:
        """``value`` as ``channel``'s contract normalises it, or :class:`CommandError` (counted, logged)."""
        c = contract or self.gate.contracts.get(channel) or _FALLBACK.get(channel)
        if c is None:
            return value
        try:
            return c.check(value)
        except ContractViolation as exc:
            raise self.refuse(channel, exc.reason, f"{key!r}: {exc} (expected {c.describe()})") from None

    # ------------------------------------------------------------------------------------------ messages
    def decode(self, raw: str | bytes | None, channel: str = COMMAND) -> dict[str, Any]:
        """A message's JSON object, or :class:`CommandError`: empty, over :data:`MAX_MESSAGE_BYTES`, not JSON
        (nested too deep included), or not an object."""
        if not raw:
            raise self.refuse(channel, "empty", "an empty message (expected a JSON object)")
        if len(raw) > MAX_MESSAGE_BYTES:
            raise self.refuse(channel, "size", f"a message of {len(raw)} bytes (at most {MAX_MESSAGE_BYTES})")
        try:
            data = json.loads(raw)
        except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            raise self.refuse(channel, "encoding", f"not JSON: {type(exc).__name__} (expected an object)") from None
        if data is None:
            raise self.refuse(channel, "empty", "null (expected a JSON object)")
        if not isinstance(data, dict):
            raise self.refuse(channel, "type", f"expected a JSON object, got a JSON {type(data).__name__}")
        return data

    def command(self, data: dict[str, Any]) -> Command:
        """Admit a decoded drive message (Donkeycar's ``angle, throttle, drive_mode, recording, buttons``, ours
        ``stop, release``). ``null`` or a missing key is "not given". Any refused value refuses the message:
        every bad value is counted, and the error names them all."""
        errors: list[str] = []
        got: dict[str, Any] = {}
        for key, channel in _VALUES.items():
            value = data.get(key)
            if value is None:
                continue
            try:
                got[key] = self._mode(value) if key == "drive_mode" else self.admit(channel, value, key)
            except CommandError as exc:
                errors.append(str(exc))
        flags: dict[str, bool] = {}
        for key, channel in _FLAGS.items():
            if data.get(key) is not None:
                try:
                    flags[key] = self.admit(channel, data[key], key, _FLAG)
                except CommandError as exc:
                    errors.append(str(exc))
        buttons = None
        if data.get("buttons") is not None:
            try:
                buttons = self._buttons(data["buttons"])
            except CommandError as exc:
                errors.append(str(exc))
        if errors:
            raise CommandError("; ".join(errors))
        return Command(
            angle=got.get("angle"),
            throttle=got.get("throttle"),
            mode=got.get("drive_mode"),
            recording=got.get("recording"),
            buttons=buttons,
            stop=flags.get("stop", False),
            release=flags.get("release", False),
        )

    def _mode(self, value: Any) -> str:
        """A drive mode: an alias Donkeycar's pages send made canonical, then the contract, then this car's modes."""
        try:
            value = normalise_mode(value, "web command 'drive_mode'")
        except ValueError:
            pass  # the contract says why, and counts it
        mode = self.admit("user/mode", value, "drive_mode")
        if mode not in self.modes:
            raise self.refuse(
                "user/mode", "choice", f"drive mode {mode!r} is not available here (modes: {list(self.modes)})"
            )
        return str(mode)

    def _buttons(self, value: Any) -> dict[str, bool]:
        """Donkeycar's ``buttons``: an object of up to 32 names (each up to 64 characters) to true or false."""
        if not isinstance(value, dict):
            raise self.refuse(BUTTONS, "type", f"'buttons' must be an object of name: true/false, got {value!r:.40}")
        if len(value) > _MAX_BUTTONS:
            raise self.refuse(BUTTONS, "size", f"{len(value)} buttons (at most {_MAX_BUTTONS})")
        for name, pressed in value.items():
            if len(name) > _MAX_BUTTON_NAME or not isinstance(pressed, bool):
                raise self.refuse(
                    BUTTONS,
                    "type",
                    f"button {name!r:.40} must be named in {_MAX_BUTTON_NAME} characters and "
                    f"be true or false, got {pressed!r:.40}",
                )
        return dict(value)


def parse_command(data: object, intake: Intake | None = None) -> Command:
    """Admit one decoded message through ``intake`` (by default the default contracts' gate, every drive mode):
    :class:`CommandError` for anything that is not a JSON object or carries a refused value."""
    if intake is None:
        intake = Intake(Contracts().gate("web"), DRIVE_MODES, time.monotonic)
    if not isinstance(data, dict):
        raise intake.refuse(COMMAND, "type", f"expected a JSON object, got {type(data).__name__}")
    return intake.command(data)
