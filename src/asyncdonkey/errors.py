"""The errors of the drive loop, under one root so a user can catch everything asyncdonkey raises.

:class:`AsyncdonkeyError` is the root. Each error also keeps the standard-library base a user would reach for
first (``ValueError`` for a bad argument, ``RuntimeError`` for a failure while driving), so code written
against Donkeycar or the standard library keeps catching what it caught before.

This module imports nothing from the package at run time: every module can import it, so every module's
errors can derive from the root without an import cycle. The tree (``+`` names the standard-library bases each
class adds; ``tests/core/test_error_tree.py`` checks that every public exception class of the package is under
the root)::

    AsyncdonkeyError                                   (Exception)
    ├── the core (asyncdonkey.errors, asyncdonkey.contracts, asyncdonkey.options, asyncdonkey.extras)
    │   ├── PartSpecError          + ValueError, AssertionError   Vehicle.add got something that cannot run
    │   ├── OutputCountError       + ValueError                   a part's return does not fit its outputs
    │   ├── ChannelCountError      + IndexError, ValueError       a multi-channel Memory write is short
    │   ├── PartTimeoutError       + TimeoutError                 an awaited part overran its timeout
    │   ├── PartError              + RuntimeError                 a part failed while driving
    │   ├── ContractViolation      + ValueError                   a value breaks its channel's contract
    │   ├── BadValue               + ValueError                   an option is not of the expected kind
    │   └── MissingExtra           + ImportError                  an optional extra is not installed
    ├── safety and time
    │   ├── SafetyProcessError     + RuntimeError                 the safety process could not start
    │   └── VirtualClockError      + RuntimeError                 the virtual clock cannot go on
    │       └── VirtualClockDeadlock, VirtualClockStall, VirtualClockBudgetExceeded, VirtualClockLivelock
    ├── hardware (asyncdonkey.hw)
    │   ├── I2CError               + OSError
    │   │   └── I2CDeviceNotFound, I2CDeviceInUse, MPUIdentityError
    │   ├── LockHeld                                              another process owns the device
    │   ├── CameraError            + RuntimeError
    │   │   └── PicameraMissing    + ImportError
    │   ├── SerialPortClosed       + ConnectionError
    │   ├── EncoderProtocolError   + ValueError
    │   ├── PinSpecError           + ValueError
    │   └── RPLidarError           + RuntimeError
    ├── parts (asyncdonkey.parts)
    │   ├── CalibrationLocked      + ValueError                   a calibration would move "stopped" mid-drive
    │   ├── PilotModelError        + ValueError
    │   ├── TubError
    │   │   ├── TubNotFoundError   + FileNotFoundError
    │   │   ├── TubFormatError     + ValueError
    │   │   │   └── TubImagePathError, McapReadError
    │   │   └── TubImageError      + OSError
    │   ├── FoxgloveServerError    + OSError
    │   ├── WebConfigError         + ValueError
    │   │   └── CommandError, CalibrationError
    │   ├── CodecError             + ValueError
    │   ├── ZenohConfigError       + ValueError
    │   └── PairExists             + ValueError
    ├── commands (asyncdonkey.commands)
    │   ├── CarFileError, ReplayError, QuantizeError
    │   └── ConvertError, ReportError   + ValueError
    └── testing
        └── Picamera2ModelHang     + AssertionError               a call that would hang the real library

One class stays outside on purpose: :class:`PartInterrupted` is a ``BaseException`` (like
``KeyboardInterrupt``) so that a part's ``except Exception`` cannot swallow the stop request it carries.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .core.drive_report import DriveReport

__all__ = [
    "AsyncdonkeyError",
    "ChannelCountError",
    "OutputCountError",
    "PartError",
    "PartInterrupted",
    "PartSpecError",
    "PartTimeoutError",
]


class AsyncdonkeyError(Exception):
    """Root of asyncdonkey's own errors."""


class PartSpecError(AsyncdonkeyError, ValueError, AssertionError):
    """``Vehicle.add`` was given something that cannot run; the message names the part and the argument.

    Also an ``AssertionError``: Donkeycar's ``Vehicle.add`` asserts on a bare-string ``inputs`` and a non-bool
    ``threaded``, and its tests (and user code) expect that type.
    """


class OutputCountError(AsyncdonkeyError, ValueError):
    """A part returned a value that does not unpack into its declared outputs."""


class ChannelCountError(AsyncdonkeyError, IndexError, ValueError):
    """A multi-channel write to ``Memory`` (``put``, ``mem[a, b] = ...``) got fewer values than channels.

    Also an ``IndexError``, which Donkeycar's ``Memory`` raises in that case, and a ``ValueError``.
    """


class PartTimeoutError(AsyncdonkeyError, TimeoutError):
    """An awaited part did not return within the ``timeout`` given to ``Vehicle.add``."""


class PartError(AsyncdonkeyError, RuntimeError):
    """A part failed while driving. ``part`` names it, ``tick`` is the loop count it failed on (0-based).

    ``report`` is the :class:`~asyncdonkey.loop.DriveReport` of the drive the failure ended (filled in once
    the car has been shut down), so a caller catching the error still gets the timing of the whole drive.
    """

    def __init__(self, part: str, tick: int | None, message: str) -> None:
        where = f" on tick {tick}" if tick is not None else " in its background task"
        super().__init__(f"part {part!r} failed{where}: {message}")
        self.part = part
        self.tick = tick
        self.report: DriveReport | None = None


class PartInterrupted(BaseException):
    """Raised inside a sync part that still held the loop thread after a stop request's grace.

    A ``BaseException`` (like ``KeyboardInterrupt``), not an ``Exception``, so a part's ``except Exception``
    does not swallow it; the drive loop catches it, counts it against the part and goes on stopping.
    """
